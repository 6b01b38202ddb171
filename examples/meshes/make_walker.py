"""Write the walk cycle of examples/pedestrian_crossing.yaml: ``walker_NNNN.ply``, one per frame.

``python examples/meshes/make_walker.py`` (from the repository root) rewrites
them: frame k is :func:`undream.scene.builtin.pedestrian` at phase k / 4 (a
stride every two frames), in canonical metres, facing +Z.
"""
from pathlib import Path

from undream.scene.builtin import pedestrian
from undream.scene.mesh import write_ply

FRAMES = 12
FRAMES_PER_CYCLE = 4


def main() -> None:
    here = Path(__file__).resolve().parent
    for k in range(FRAMES):
        write_ply(pedestrian(k / FRAMES_PER_CYCLE), here / f"walker_{k:04d}.ply")


if __name__ == "__main__":
    main()
