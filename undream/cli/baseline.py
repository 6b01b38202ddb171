"""``undream baseline``: the pasted-patch pipeline a run is compared with (:mod:`scheduler.baseline`)."""
from __future__ import annotations

from pathlib import Path

import click

from undream.cli.errors import one_line_errors
from undream.cli.options import force_option, local_settings, out_option, progress_option


@click.command("baseline")
@click.argument("run_yaml", type=click.Path(path_type=Path))
@out_option("Output directory (baseline.json, patch.png).")
@force_option
@progress_option
@one_line_errors
def baseline_cmd(run_yaml: Path, out: Path, force: bool, progress: bool) -> None:
    """Optimise a flat patch in image space on RUN_YAML's attacked frames (same victim, loss, ε, PGD
    steps), then wear it as the texture and judge it in the simulator on attacked and held-out frames."""
    from scheduler.baseline import run_patch_baseline
    from undream.spec.run import load_run_config

    config = load_run_config(run_yaml)
    res = run_patch_baseline(config, out, run_yaml.parent, force=force, progress=progress,
                             source=run_yaml, local=local_settings())
    image = res["in_image_space"]
    click.echo(f"in image space ({len(image['frames'])} attacked frames): {image['metric']} {_fmt(image['value'])}")
    for split, judged in res["in_simulator"].items():
        benign = res["benign"][split]["value"]
        click.echo(f"in the simulator, {split.replace('_', '-')} frames ({len(judged['frames'])}): "
                   f"{judged['metric']} benign {_fmt(benign)} → patch {_fmt(judged['value'])}")
    click.echo(f"results in {Path(out) / 'baseline.json'}")


def _fmt(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.3f}"


COMMANDS = (baseline_cmd,)
