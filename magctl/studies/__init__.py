"""Studies: the runner of ``analysis/``, batches of push trials and their reductions, the report, animations."""
