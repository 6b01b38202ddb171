"""The run store: attack-run state in SQL (SQLite or PostgreSQL), arrays as blob files.

``open_store(url, blob_dir)`` gives a :class:`Store`; every read and write of a
run's state (runs, textures, frame jobs, gradients, iteration records, attack
states) goes through it. See :mod:`undream.store.store` for the contract.
"""
from __future__ import annotations

from undream.store.blobs import (
    BlobStore, attack_state_key, blob_root, check_key, eval_image_key, grad_key, run_prefix,
    scene_key, texture_blob_key,
)
from undream.store.checks import RECORD_FIELDS
from undream.store.db import NoDatabase, make_engine, mask_url, open_store
from undream.store.jobs import UNFINISHED, EvalResult, JobResult
from undream.store.models import JOB_PHASES, JOB_STATUSES, RUN_STATUSES, SCHEMA_VERSION
from undream.store.newrun import NewRun
from undream.store.pages import MAX_PAGE, RunPage
from undream.store.snapshots import (
    FrameGrad, IterationSnapshot, JobLine, JobSnapshot, RunSnapshot, SweepSnapshot,
)
from undream.store.store import ACTIVE, TRANSITIONS, Store

__all__ = [
    "ACTIVE", "BlobStore", "EvalResult", "FrameGrad", "IterationSnapshot", "JOB_PHASES", "JOB_STATUSES",
    "JobLine", "JobResult", "JobSnapshot", "MAX_PAGE", "NewRun", "NoDatabase", "RECORD_FIELDS", "RUN_STATUSES",
    "RunPage", "RunSnapshot", "SCHEMA_VERSION", "Store",
    "SweepSnapshot", "TRANSITIONS", "UNFINISHED", "attack_state_key", "blob_root", "check_key",
    "eval_image_key", "grad_key", "make_engine", "mask_url", "open_store", "run_prefix",
    "scene_key", "texture_blob_key",
]
