"""The ``viewloc`` command line: learn, match, serve, worker, bench."""
