"""The run store: attack-run state in SQL (SQLite or PostgreSQL), arrays as blob files.

``open_store(url, blob_dir)`` gives a :class:`Store`; every read and write of a
run's state (runs, textures, frame jobs, gradients, iteration records, attack
states) goes through it. See :mod:`undream.store.store` for the contract.
"""
from __future__ import annotations

from undream.store.blobs import (
    BlobStore, attack_state_key, check_key, grad_key, run_prefix, texture_blob_key,
)
from undream.store.db import make_engine, mask_url, open_store
from undream.store.models import JOB_STATUSES, RUN_STATUSES
from undream.store.snapshots import FrameGrad, IterationSnapshot, JobSnapshot, RunSnapshot
from undream.store.store import RECORD_FIELDS, TRANSITIONS, Store

__all__ = [
    "BlobStore", "FrameGrad", "IterationSnapshot", "JOB_STATUSES", "JobSnapshot",
    "RECORD_FIELDS", "RUN_STATUSES", "RunSnapshot", "Store", "TRANSITIONS",
    "attack_state_key", "check_key", "grad_key", "make_engine", "mask_url", "open_store",
    "run_prefix", "texture_blob_key",
]
