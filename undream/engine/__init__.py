"""Algorithm 1 as plain functions: the per-frame job and reduce-and-step.

They read and write run state only through :mod:`undream.store`, so the farm
wraps them in Celery tasks and a chord without changing them; the in-process
runner (:mod:`scheduler.local`) calls them in a loop.
"""
