"""The benchmark: POV-Ray test sets (the paper's §5.1 and a harder one), LM-O real
photos, and the runner behind ``make bench`` (``python -m viewloc_bench``)."""
