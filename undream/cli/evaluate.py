"""``undream evaluate``: a texture judged on any scenes, victims and simulator (:mod:`scheduler.evaluate`)."""
from __future__ import annotations

import csv
import io
import json
from pathlib import Path

import click

from undream.cli.errors import one_line_errors
from undream.cli.options import local_settings, spp_option
from undream.errors import SpecError


@click.command("evaluate")
@click.argument("texture", type=click.Path(path_type=Path))
@click.argument("scenes", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--victim", "victims", multiple=True, default=("bundled:classifier",), show_default=True,
              help="A victim (bundled:NAME, a folder or a hub id); repeat for several.")
@click.option("--sim", default="mitsuba", show_default=True, help="The simulator that renders: mitsuba or blender.")
@spp_option("--spp", 32, "Samples per pixel of every frame.")
@click.option("--holdout", default="auto", show_default=True,
              help="Which frames a run would hold out (auto: every 4th; none), judged apart.")
@click.option("--label", default=None, help="The object's class (default: the scene's).")
@click.option("--json", "json_out", type=click.Path(path_type=Path), default=None, help="Write the rows as JSON.")
@click.option("--csv", "csv_out", type=click.Path(path_type=Path), default=None, help="Write the rows as CSV.")
@one_line_errors
def evaluate_cmd(texture: Path, scenes: tuple[Path, ...], victims: tuple[str, ...], sim: str, spp: int,
                 holdout: str, label: str | None, json_out: Path | None, csv_out: Path | None) -> None:
    """Judge TEXTURE (a .npy, a .png, or an `undream run` output folder) on SCENES (scene directories
    or spec files) by each victim, rendered by one simulator: per scene and victim, on every frame
    and apart on the frames a run would attack and hold out, beside the scene's own texture."""
    from scheduler.evaluate import evaluate, read_texture, run_scene

    for flag, path in (("--json", json_out), ("--csv", csv_out)):  # before the renders, not after
        if path is not None and not path.parent.is_dir():
            raise SpecError(f"{flag} {path}: its folder {path.parent} does not exist")
    rows = evaluate(read_texture(texture), scenes, victims, sim=sim, spp=spp, holdout=holdout, label=label,
                    local=local_settings(), reference=run_scene(texture) if texture.is_dir() else None)
    click.echo(_table(rows))
    if json_out is not None:
        json_out.write_text(json.dumps({"texture": str(texture), "rows": rows}, indent=2, allow_nan=False) + "\n")
    if csv_out is not None:
        buf = io.StringIO()
        writer = csv.DictWriter(buf, fieldnames=list(rows[0]), lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
        csv_out.write_text(buf.getvalue())


def _table(rows: list[dict]) -> str:
    lines = [f"{'scene':<28} {'victim':<22} {'sim':<8} {'split':<9} {'frames':>6}  metric     benign → texture"]
    for r in rows:
        benign = "n/a" if r["benign"] is None else f"{r['benign']:.3f}"
        adv = "n/a" if r["adversarial"] is None else f"{r['adversarial']:.3f}"
        lines.append(f"{Path(r['scene']).name[:28]:<28} {r['victim'][-22:]:<22} {r['sim']:<8} {r['split']:<9} "
                     f"{r['frames']:>6}  {r['metric']:<10} {benign} → {adv}")
    return "\n".join(lines)


COMMANDS = (evaluate_cmd,)
