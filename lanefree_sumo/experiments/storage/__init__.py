"""Where results live: run and output folders (:mod:`.rundir`, the one module that knows their file names), the
episode log, one run's data as the analyses read it, trajectory files."""
