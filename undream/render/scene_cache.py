"""One loaded Mitsuba scene per group of structurally equal frames, per process.

Dr.Jit traces its symbolic calls over every shape, BSDF and emitter registered
in the process, so a render costs more with every scene kept loaded (measured:
a 64 px gradient render 0.065 s with one scene loaded, 1.33 s with 62 more).
A sequence's frames usually differ only in numbers that ``mi.traverse``
exposes: the camera's and the actors' transforms (mesh vertices), the sun,
sky and lamp, the fog's density. Frames whose scene files are equal up to
those numbers form a *group*; the cache keeps one scene per group loaded and
switches frames by writing the frame's parameter values into it.

A frame's values are read once, by loading its own file and dropping it
again (a dropped scene leaves the registry). Frames whose files differ in
anything else (film size, integrator, a fog medium in some frames, another
mesh) land in another group; a frame whose scene exposes different parameter
names or differs in a host-side (non-JIT) parameter starts a group of its own.
"""
from __future__ import annotations

import gc
import re
import weakref
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any, Iterator

import numpy as np

from undream import interrupts
from undream.errors import RenderError
from undream.lru import LRU, LastArray
from undream.render.loading import load_scene, texture_param_key
from undream.scene.layout import frame_xml
from undream.variant import mitsuba

FROZEN_WARN_AFTER = 64  # Dr.Jit warns when one frozen function was recorded more often than this
KINDS = ("sim", "grad", "mask")  # mask: the init's visibility scenes (frames/mask_NNNN.xml while it verifies)

# Numbers in these elements become traversable parameters once loaded (transforms,
# emitter and medium values, sphere placement); everything else is structure.
_VARYING = re.compile(
    r'(<matrix value=|<rgb name="[a-z_0-9]+" value=|<float name="(?:sigma_t|radius)" value=)"[^"]*"'
    r'|(<vector name="(?:direction|position|center)") x="[^"]*" y="[^"]*" z="[^"]*"')
# A per-frame mesh (meshes/NAME_NNNN.ply): its buffers (vertex positions, normals, UVs, faces)
# are traversable too. Frames whose meshes have buffers of the same sizes join one group and get
# their buffers written per frame like any other value; other sizes start a group (_differences).
_PER_FRAME_MESH = re.compile(r'(<string name="filename" value="[^"]*/meshes/[^"/]*_)\d{4,}(\.ply")')


def structure_key(xml_text: str) -> str:
    """The scene file with the numbers that ``mi.traverse`` can change per frame blanked out."""
    text = _PER_FRAME_MESH.sub(lambda m: m.group(1) + "#" + m.group(2), xml_text)
    return _VARYING.sub(lambda m: (m.group(1) or m.group(2)) + ' "#"', text)


@dataclass
class ActiveFrame:
    """A loaded scene showing one frame: ``params`` is its ``mi.traverse``; ``texture_key`` the texture's key."""

    scene: Any
    params: Any
    texture_key: str | None  # None in a mask scene (no texture)
    index: int


@dataclass
class _Group:
    representative: int  # frame index whose file was loaded
    loaded: ActiveFrame | None = None
    base: dict[str, Any] = field(default_factory=dict)  # representative's values of the JIT parameters
    applied: set[str] = field(default_factory=set)  # keys currently holding another frame's values
    # the representative's values as numpy (None where they have none), read once per group for the
    # comparisons of every other frame (each conversion waits on Dr.Jit: 4 a key per frame made
    # half of a frame's first use)
    as_numpy: dict[str, np.ndarray | None] = field(default_factory=dict)

    def theirs(self, key: str) -> tuple[Any, np.ndarray | None]:
        """The representative's value of ``key`` and its numpy form (cached); the group is loaded."""
        assert self.loaded is not None
        value = self.base.get(key, self.loaded.params[key])
        if key not in self.as_numpy:
            self.as_numpy[key] = _numpy_or_none(value)
        return value, self.as_numpy[key]


@dataclass
class _FrameState:
    group: tuple[str, int]  # (structure key, sub-group number)
    values: dict[str, Any]  # parameter key → value where the frame differs from its group's representative


class SceneCache:
    """A scene directory's ``sim`` and ``grad`` scenes, loaded once per group of equal frames.

    ``max_loaded`` bounds the scenes kept loaded at once (least recently used
    ones are dropped and reloaded when needed again; a drop also clears the
    frozen recordings). 8: a multi-condition scene's weathers × backgrounds make
    several sim groups besides the gradient one, and with 4 a 16-condition run
    dropped and re-recorded scenes at every iteration (measured on the scene of
    examples/runs/bin_orbit_conditions.yaml: 270 ms per frame's render and
    capture with 4, 40–90 ms with 8). ``frozen`` runs the
    renders as Dr.Jit frozen functions (default: on; the edge passes
    ``UNDREAM_FROZEN=0`` as False). ``share=False`` gives every frame a scene of
    its own (the engine's former behaviour, kept for benchmarks and tests).
    """

    def __init__(self, scene_dir: str | Path, mi: ModuleType | None = None, max_loaded: int = 8,
                 frozen: bool = True, share: bool = True):
        self.dir = Path(scene_dir)
        self.mi = mi or mitsuba()
        self.max_loaded = max_loaded
        self.share = share
        self.frozen = bool(frozen)
        self._frozen: dict[tuple[str, int | None], Any] = {}  # (name, id of its scene) → frozen function
        self.render_texture: LastArray[Any] = LastArray()  # the last sRGB texture rendered → its tensor
        # (frame index, spp) → the frame rendered whole with the scene's own texture (undream.engine.crops)
        self.bases: dict[tuple[int, int], np.ndarray] = {}
        self._groups: dict[tuple[str, tuple[str, int]], _Group] = {}
        self._states: dict[tuple[str, int], _FrameState] = {}
        # the loaded groups; _make_room drops the least recently used before a load, so put() drops none
        # the LRU calls back through a weak reference: with a bound method the cache referred to itself,
        # and a dropped cache kept its scenes registered (every render in the process tracing over
        # their shapes) until the collector's rare full pass, then was freed wherever that ran
        unload = weakref.WeakMethod(self._unload)
        self._lru: LRU[tuple[str, tuple[str, int]], _Group] = LRU(
            max(1, max_loaded), on_evict=lambda key, group: _call_alive(unload, key, group))

    def close(self) -> None:
        """Drop the frozen recordings, then the loaded scenes (in that order: recordings refer to scenes)."""
        for f in self._frozen.values():
            f.clear()
        self._frozen.clear()
        self.render_texture.clear()
        self.bases.clear()
        for group in self._groups.values():
            group.loaded = None
        self._lru.clear()

    def __del__(self) -> None:
        # The garbage collector runs this wherever Python allocates, also inside another cache's
        # frozen recording (a test's cache collected during the next test's init render): clearing
        # recordings there made Dr.Jit terminate the process ("RecordThreadState::enqueue_host_func():
        # this function cannot be recorded!"). There the recordings and scenes are only let go,
        # which Dr.Jit allows; close() is for everywhere else.
        try:
            import drjit as dr

            if not dr.flag(dr.JitFlag.FreezingScope):
                self.close()
        except Exception:  # interpreter shutdown: modules may already be gone
            pass

    @property
    def loaded_count(self) -> int:
        """How many Mitsuba scenes this cache keeps loaded now."""
        return sum(g.loaded is not None for g in self._groups.values())

    def frozen_call(self, name: str, fn: Any, *args: Any, scene: Any = None) -> Any:
        """``fn(*args)`` as a Dr.Jit frozen function (one per ``name`` and loaded ``scene``): recorded,
        then replayed. Per scene, so that dropping a scene drops only its own recordings (a
        multi-condition scene keeps several groups loaded; the 16-condition example printed Dr.Jit's
        "recorded N times" warnings with one function for all, none with one per scene).

        A SIGTERM, SIGHUP or Ctrl-C arriving while it records or replays is raised when the call ends
        (:func:`undream.interrupts.held`): raised inside the recording, Dr.Jit turned its exception
        into a RuntimeError ("error encountered while recording a frozen function") and the command
        printed 65 lines and exited 1 instead of ending as Ctrl-C does (exit 143 for SIGTERM).

        Python's garbage collector is paused while it records or replays
        (:func:`collector_paused`)."""
        import drjit as dr

        key = (name, None if scene is None else id(scene))
        if key not in self._frozen:
            # Conditions of one structure share a loaded scene, and Dr.Jit records again when the
            # values it saw as constants change (auto_opaque): the evaluation of
            # examples/runs/stop_sign_main.yaml (10 conditions) recorded its render 12 times, and
            # the default warning after 10 printed a paragraph into the main job's output.
            self._frozen[key] = dr.freeze(fn, warn_after=FROZEN_WARN_AFTER)
        with interrupts.held(), collector_paused():
            return self._frozen[key](*args)

    def group_count(self, kind: str) -> int:
        """How many groups of ``kind`` the frames seen so far fall into."""
        return sum(k == kind for k, _ in self._groups)

    def loaded(self, kind: str, index: int) -> ActiveFrame:
        """The loaded scene of frame ``index``'s group, as it is (showing whichever frame it shows)."""
        if kind not in KINDS:
            raise RenderError(f"scene kind must be one of {KINDS}, got {kind!r}")
        gkey = (kind, self._state(kind, index).group)
        return self._ensure_loaded(kind, gkey, self._groups[gkey])

    def frame(self, kind: str, index: int, conditions: Any = None, texture: Any = None) -> ActiveFrame:
        """The scene of ``kind`` ('sim' or 'grad') showing frame ``index``.

        ``conditions`` (:class:`undream.render.jitter.Conditions`): the frame's
        camera and light moved by them for the next render only; the next call
        writes the frame's own values back. ``texture``: a tensor for the
        texture parameter, written in the same scene update as the frame's values.
        """
        if kind not in KINDS:
            raise RenderError(f"scene kind must be one of {KINDS}, got {kind!r}")
        state = self._state(kind, index)
        gkey = (kind, state.group)
        group = self._groups[gkey]
        active = self._ensure_loaded(kind, gkey, group)
        extra = {} if texture is None else {active.texture_key: texture}
        if active.index != index:  # already showing it: nothing to write, no BVH to rebuild
            self._apply(group, active, state, extra)
            active.index = index
        elif extra:
            active.params[active.texture_key] = texture
            update_params(active.params)
        if conditions is not None:
            self._jitter(group, active, conditions)
        return active

    def _jitter(self, group: _Group, active: ActiveFrame, conditions: Any) -> None:
        from undream.render.jitter import jitter_values

        values = {k: v for k, v in jitter_values(self.mi, active.params, conditions).items() if k in group.base}
        for key, value in values.items():
            active.params[key] = value
        update_params(active.params)
        group.applied |= set(values)  # reset to the frame's own values by the next _apply
        active.index = -1  # not showing any frame as it is

    # -- frame states -------------------------------------------------------

    def _state(self, kind: str, index: int) -> _FrameState:
        if (kind, index) in self._states:
            return self._states[(kind, index)]
        xml = frame_xml(self.dir, kind, index)
        if not xml.is_file():
            raise RenderError(f"{xml}: no such frame file (is {self.dir} a scene directory?)")
        skey = structure_key(xml.read_text()) if self.share else f"frame {index}"
        sub = 0
        while True:
            gkey = (kind, (skey, sub))
            group = self._groups.get(gkey)
            if group is None:
                self._groups[gkey] = _Group(representative=index)
                state = _FrameState((skey, sub), {})
                break
            values = self._differences(kind, gkey, group, xml)
            if values is not None:
                state = _FrameState((skey, sub), values)
                break
            sub += 1  # differs in a way traversal cannot express: a group of its own
        self._states[(kind, index)] = state
        return state

    def _differences(self, kind: str, gkey, group: _Group, xml: Path) -> dict[str, Any] | None:
        """The frame's JIT parameter values that differ from the group's; None if it cannot join."""
        self._ensure_loaded(kind, gkey, group)
        scene = load_scene(self.mi, xml, spp=1, merge=False)
        try:
            params = self.mi.traverse(scene)
            if set(params.keys()) != set(group.loaded.params.keys()):
                return None
            out = {}
            for key in params.keys():
                if key == group.loaded.texture_key:
                    continue
                mine = params[key]
                theirs, theirs_np = group.theirs(key)
                mine_np = _numpy_or_none(mine)
                if mine_np is None or theirs_np is None:  # not an array: compared as Python values
                    same_size, equal = True, bool(mine == theirs)
                else:
                    same_size, equal = mine_np.shape == theirs_np.shape, np.array_equal(mine_np, theirs_np)
                if key not in group.base:  # host-side value: must be equal
                    if not equal:
                        return None
                elif not same_size:  # another mesh: a buffer cannot change its size
                    return None
                elif not equal:
                    out[key] = _copy(mine)
            return out
        finally:
            del params, scene

    # -- loading and switching ----------------------------------------------

    def _ensure_loaded(self, kind: str, gkey, group: _Group) -> ActiveFrame:
        if group.loaded is None:
            self._make_room()
            scene = load_scene(self.mi, frame_xml(self.dir, kind, group.representative), spp=1, merge=False)
            params = self.mi.traverse(scene)
            texture_key = None if kind == "mask" else texture_param_key(params)  # the mask's object emits
            group.loaded = ActiveFrame(scene, params, texture_key, group.representative)
            group.base = {k: _copy(params[k]) for k in params.keys()
                          if _is_jit(params[k]) and k != group.loaded.texture_key}
            group.applied = set()
            group.as_numpy = {}
        self._lru.put(gkey, group)
        return group.loaded

    def _make_room(self) -> None:
        while self.loaded_count >= self.max_loaded and self._lru:
            self._lru.drop_oldest()

    def _unload(self, gkey: tuple[str, tuple[str, int]], group: _Group) -> None:
        if group.loaded is not None:  # the recordings that may refer to the scene being dropped
            for key in [k for k in self._frozen if k[1] in (id(group.loaded.scene), None)]:
                self._frozen.pop(key).clear()
        group.loaded = None

    def _apply(self, group: _Group, active: ActiveFrame, state: _FrameState,
               extra: dict[str, Any] | None = None) -> None:
        keys = set(state.values) | group.applied
        if not keys and not extra:
            return
        for key in keys:
            active.params[key] = state.values.get(key, group.base[key])
        for key, value in (extra or {}).items():
            active.params[key] = value
        update_params(active.params)
        group.applied = set(state.values)


def _call_alive(method: weakref.WeakMethod, *args: Any) -> None:
    """``method(*args)`` if its object still lives."""
    bound = method()
    if bound is not None:
        bound(*args)


@contextmanager
def collector_paused() -> Iterator[None]:
    """Python's garbage collector off for the block (on again after it if it was on).

    A dropped scene cache was garbage only the collector freed (its LRU called back into it), and the
    collector runs wherever Python allocates: inside a Dr.Jit recording, freeing a dropped cache's
    scenes and recordings there made Dr.Jit terminate the process ("RecordThreadState::
    enqueue_host_func(): this function cannot be recorded!"): a test process of the whole suite died
    of it, and a worker whose cache dropped scenes could have. Caches are freed when dropped now, but
    other garbage may hold one. What is unreachable meanwhile is freed at the next collection after
    the block."""
    was_on = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was_on:
            gc.enable()


def update_params(params: Any) -> None:
    """``params.update()`` (Mitsuba's ``SceneParameters``) without its walk over every parameter.

    Mitsuba's update schedules the value of each of the scene's parameters (113 in the main job's
    scene) before it notifies the objects that changed; the values this module writes are already
    evaluated, so only the notification is needed: the written keys marked dirty (those
    ``__setitem__`` did not mark itself), each changed object's ``parameters_changed`` from the
    leaves up, one ``dr.eval()``. Half of a 64 px frame switch's 1.2 ms (measured, loaded machine).
    A Mitsuba whose ``SceneParameters`` lacks the attributes read here gets its own ``update()``.
    """
    import drjit as dr

    candidates = getattr(params, "update_candidates", None)
    nodes = getattr(params, "nodes_to_update", None)
    get = getattr(params, "_SceneParameters__get_value", None)
    try:
        from mitsuba.python.util import _jit_id_hash
    except ImportError:
        _jit_id_hash = None
    if candidates is None or nodes is None or get is None or _jit_id_hash is None:
        params.update()
        return
    for key in list(candidates):
        if _jit_id_hash(get(key)) != candidates[key]:  # changed in place since it was read
            params.set_dirty(key)
    for _, node, keys in sorted(((d, n, k) for (d, n), k in nodes.items()), key=lambda x: x[0], reverse=True):
        node.parameters_changed(list(keys))
    nodes.clear()
    candidates.clear()
    dr.eval()


def _is_jit(value: Any) -> bool:
    """A per-frame value Dr.Jit holds on the device (not a host-side scalar or a tensor)."""
    import drjit as dr

    inner = value.matrix if hasattr(value, "matrix") else value
    return dr.is_array_v(inner) and not dr.is_tensor_v(inner) and dr.backend_v(inner) != dr.JitBackend.Invalid


def _copy(value: Any) -> Any:
    import drjit as dr

    return type(value)(value) if dr.is_array_v(value) or hasattr(value, "matrix") else value


def _as_numpy(value: Any) -> np.ndarray:
    if hasattr(value, "matrix"):
        value = value.matrix
    return np.asarray(np.array(value), dtype=np.float64)


def _numpy_or_none(value: Any) -> np.ndarray | None:
    """``value`` as a float64 array, or None where it has no array form (a string, a plugin)."""
    try:
        return _as_numpy(value)
    except (TypeError, ValueError):
        return None
