"""Frozen scene-model dataclasses (no heavy imports) and their JSON form."""
from undream.spec.io import load_sequence, save_sequence
from undream.spec.model import (
    BACKGROUNDS,
    WEATHERS,
    ActorPose,
    Asset,
    Camera,
    Condition,
    Environment,
    Frame,
    Sequence,
    TextureParam,
    Transform,
    sun_direction,
)

__all__ = [
    "ActorPose", "Asset", "BACKGROUNDS", "Camera", "Condition", "Environment", "Frame", "Sequence",
    "TextureParam", "Transform", "WEATHERS", "load_sequence", "save_sequence", "sun_direction",
]
