"""The ``undream`` command line: ``init``, ``run``, the farm's commands (:mod:`undream.cli.farm`:
``submit``, ``worker``, ``status``, ``cancel``, ``resume``, ``sweep``, ``results``), ``dashboard``
(:mod:`undream.cli.dashboard`), ``report`` (:mod:`undream.cli.report`), ``export`` (:mod:`undream.cli.export`) and the ``victims`` group
(:mod:`undream.cli.victims`).

Errors are mapped at this edge (:mod:`undream.cli.errors`): one line on stderr, exit status 2.
"""
from __future__ import annotations

from pathlib import Path

import click

from undream.cli.baseline import COMMANDS as BASELINE
from undream.cli.dashboard import COMMANDS as DASHBOARD
from undream.cli.errors import OneLineGroup, one_line_errors
from undream.cli.evaluate import COMMANDS as EVALUATE
from undream.cli.export import COMMANDS as EXPORT
from undream.cli.farm import COMMANDS
from undream.cli.options import check_option, force_option, local_settings, out_option, progress_option, spp_option
from undream.cli.report import COMMANDS as REPORT
from undream.cli.victims import victims
from undream.errors import SpecError


@click.group(cls=OneLineGroup)
@click.version_option(package_name="undream")
def main() -> None:
    """undream: adversarial textures for 3D objects, judged in the simulator."""


@main.command("init")
@click.argument("spec", type=click.Path(path_type=Path))
@out_option("Scene directory to write.")
@force_option
@spp_option("--verify-spp", 16, "Samples per pixel of the verification renders.")
@spp_option("--scene-spp", 64, "Default samples per pixel written into the scene XML files.", most=65536)
@click.option("--object", "object_name", default=None, metavar="NAME",
              help="For a .blend SPEC: the adversarial object (a UV-mapped mesh object's name).")
@click.option("--camera", default=None, metavar="NAME",
              help="For a .blend SPEC: the camera object (default: the scene's active camera).")
@click.option("--actor", "actors", multiple=True, metavar="NAME",
              help="For a .blend SPEC: a mesh object to bring along as an actor (repeatable).")
@check_option
@progress_option
@one_line_errors
def init_cmd(spec: Path, out: Path, force: bool, verify_spp: int, scene_spp: int, object_name: str | None,
             camera: str | None, actors: tuple[str, ...], check: bool, progress: bool) -> None:
    """Write the scene directory of SPEC (trajectory YAML, Unreal export JSON, sequence.json, or a
    Blender .blend with --object NAME)."""
    from scheduler.preflight import SCENE_MARKER, check_output_folder
    from undream.bridge.blender_import import BlendSource
    from undream.scenedir.init import InitOptions, Source, check_init, init_scene

    local = local_settings()
    source: Source = spec
    if spec.suffix.lower() == ".blend" and object_name:
        source = BlendSource(spec, object_name, camera, actors, python=local.blender_python,
                             cache_dir=str(Path(local.cache_home) / "undream" / "blend"), env=local.child_env)
    elif spec.suffix.lower() != ".blend" and (object_name or camera or actors):
        raise SpecError(f"{spec}: --object, --camera and --actor are for .blend files only")
    options = InitOptions(force=force, verify_spp=verify_spp, scene_spp=scene_spp, progress=progress,
                          memory_limit=local.memory_limit, frozen=local.frozen, cache_dir=local.undream_cache)
    check_output_folder(out, None, force, command="undream init", marker=SCENE_MARKER,
                        inputs=(spec,))  # the one output-folder rule
    if check:
        click.echo(f"ok: {spec} can be written to {out}: {check_init(source, out, options).describe()}; "
                   f"nothing written; {UNSEEN_NOT_CHECKED}")
        return
    done = init_scene(source, out, options)
    click.echo(f"wrote {done} (contact sheet: {done / 'verify' / 'contact_sheet.png'})")


# --check renders nothing: whether a spec's object is seen (in every condition) is known once its
# masks are rendered, which `undream init` (and `undream run` on a spec) does before writing.
UNSEEN_NOT_CHECKED = ("whether a frame (of each condition) shows the object is checked when its masks are "
                      "rendered, not by --check")


@main.command("run")
@click.argument("run_yaml", type=click.Path(path_type=Path))
@out_option("Output directory.")
@force_option
@click.option("--resume", is_flag=True,
              help="Continue the run recorded in --out (after a crash or Ctrl-C) from its last iteration.")
@check_option
@progress_option
@one_line_errors
def run_cmd(run_yaml: Path, out: Path, force: bool, resume: bool, check: bool, progress: bool) -> None:
    """Run the attack of RUN_YAML in this process (embedded defaults: Mitsuba, SQLite)."""
    from undream.spec.run import load_run_config

    config = load_run_config(run_yaml)  # a malformed config is one line before the farm's modules and torch load
    from scheduler.local import check_run, run_local
    from scheduler.preflight import is_scene, scene_source

    local = local_settings()
    if check:
        estimate = check_run(config, out, base_dir=run_yaml.parent, force=force, source=run_yaml, local=local)
        masks = config.conditions is None and is_scene(scene_source(config, run_yaml.parent))  # rendered, checked
        click.echo(f"ok: {run_yaml} is valid: {estimate.describe()}; nothing written"
                   + ("" if masks else f"; {UNSEEN_NOT_CHECKED}"))
        return
    res = run_local(config, out, base_dir=run_yaml.parent, progress=progress, force=force, resume=resume,
                    source=run_yaml, local=local)
    for name, split in (("attacked frames", res.get("attacked")), ("held-out frames", res.get("held_out")),
                        ("held-out conditions", res.get("held_out_conditions"))):
        if split:
            b, a = split["benign"], split["adversarial"]
            click.echo(f"{name} ({len(split['frames'])}): {b['metric']} benign {_fmt(b['value'])} → "
                       f"adversarial {_fmt(a['value'])}")
    b, a = res["benign"], res["adversarial"]
    click.echo(f"{b['metric']}: benign {_fmt(b['value'])} → adversarial {_fmt(a['value'])}; "
               f"results in {out / 'results.json'}")


def _fmt(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.3f}"


def _register_subgroups() -> None:
    main.add_command(victims)
    for command in COMMANDS + DASHBOARD + REPORT + BASELINE + EVALUATE + EXPORT:
        main.add_command(command)


_register_subgroups()
