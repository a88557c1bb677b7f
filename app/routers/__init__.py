"""Thin routers: parse, validate, call one store or core function, serialise."""
