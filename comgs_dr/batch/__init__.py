"""``comgs batch``: jobs (reconstruct, decompose, compose, render-comp) as a Ray task graph,
and ``comgs render-comp --ray``: one render's frames split over Ray workers (docs/batch.md).

``spec``: the jobs file, read and checked; ``tasks``: what each Ray task runs (a stage
function, in-process); ``graph``: the task graph, its retries and its summary.
"""
from comgs_dr.batch.graph import render_sharded, run_batch
from comgs_dr.batch.spec import JobsFileError, load_jobs

__all__ = ["JobsFileError", "load_jobs", "render_sharded", "run_batch"]
