"""Algorithm 1's library side: a run's context, the per-frame job, and evaluation.

Plain functions without Celery, a database or a broker. :mod:`scheduler.iteration`
reads and writes run state around them through :mod:`undream.store`; the farm
wraps those in Celery tasks, the in-process runner (:mod:`scheduler.local`)
calls them in a loop.
"""
