"""``python -m viewloc_cli``.

The guard matters: the job runner starts its workers with the 'spawn' method,
which re-imports the main module in every child.
"""

from viewloc_cli.main import main

if __name__ == "__main__":
    raise SystemExit(main())
