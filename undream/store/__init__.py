"""The run store: attack-run state in SQL (SQLite or PostgreSQL), arrays as blobs.

Blobs live in a folder, the run database or S3-compatible storage behind one
interface (:class:`BlobStore`). ``open_store(url, blob_url)`` (or
``open_farm_store(settings)``) gives a :class:`Store`; every read and write of a
run's state (runs, textures, frame jobs, gradients, iteration records, attack
states) goes through it. See :mod:`undream.store.store` for the contract.
"""
from __future__ import annotations

from undream.store.blobs import (
    DATABASE, BlobOptions, BlobStore, attack_state_key, blob_root, check_key, eval_image_key, grad_key,
    parse_blob_url, run_prefix, scene_key, texture_blob_key,
)
from undream.store.checks import RECORD_FIELDS
from undream.store.db import NoDatabase, make_engine, mask_url, open_farm_store, open_store
from undream.store.jobs import UNFINISHED, EvalResult, JobResult
from undream.store.models import JOB_PHASES, JOB_STATUSES, RUN_STATUSES, SCHEMA_VERSION
from undream.store.newrun import NewRun
from undream.store.pages import MAX_PAGE, BadCursor, RunPage
from undream.store.snapshots import (
    FrameGrad, IterationSnapshot, JobLine, JobSnapshot, RunSnapshot, SweepSnapshot,
)
from undream.store.store import ACTIVE, TRANSITIONS, Store

__all__ = [
    "ACTIVE", "BadCursor", "BlobOptions", "BlobStore", "DATABASE", "EvalResult", "FrameGrad", "IterationSnapshot", "JOB_PHASES",
    "JOB_STATUSES", "JobLine", "JobResult", "JobSnapshot", "MAX_PAGE", "NewRun", "NoDatabase", "RECORD_FIELDS",
    "RUN_STATUSES", "RunPage", "RunSnapshot", "SCHEMA_VERSION", "Store",
    "SweepSnapshot", "TRANSITIONS", "UNFINISHED", "attack_state_key", "blob_root", "check_key",
    "eval_image_key", "grad_key", "make_engine", "mask_url", "open_farm_store", "open_store", "parse_blob_url", "run_prefix",
    "scene_key", "texture_blob_key",
]
