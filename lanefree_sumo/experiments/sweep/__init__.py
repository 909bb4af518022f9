"""``lanefree sweep``: grids of training runs (the paper's Tables 5–8) on Ray, resumable.

A sweep folder ``DIR`` holds::

    sweep.yaml            the manifest: the resolved grid, its budget against the paper's, sessions
    runs/<algo>_<preset>_d<density>_s<seed>/   one ordinary run folder per cell (``lanefree train``'s)
    logs/<run>.log        what each run's worker printed, every attempt appended
    summary.csv, summary.md, curves/table<N>_<metric>.png   the results (:mod:`.summary`)
    .sweep/               machine state: driver lock, heartbeats of running runs, failure reasons

Modules: :mod:`.grid` (built-in and YAML grids, validation), :mod:`.manifest` (``sweep.yaml``,
paths, the driver lock), :mod:`.state` (what each run folder holds, heartbeats, locks),
:mod:`.worker` (the Ray task: one run in one fresh process), :mod:`.runner` (the Ray driver,
progress, Ctrl-C), :mod:`.summary` (bootstrap CIs, plots), :mod:`.command` (the CLI verb).
Nothing here imports Ray, torch or SB3 at import time.
"""
