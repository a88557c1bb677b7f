"""viewloc HTTP service (FastAPI): parses, validates, calls core and store, serialises."""
