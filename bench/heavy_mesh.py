"""A heavier scene for traversal figures: cornell-box with its tall box
replaced by a bumpy ball of about 100 k triangles.

    python bench/heavy_mesh.py --out /tmp/cornell-mesh.json   # the scene as JSON

cornell-box has 36 triangles: every ray there meets the same few nodes, so
its rays/s say little about a BVH's build or memory layout. Here most rays
that reach the ball walk a tree of ~50 k nodes (several MB of node and
triangle data, more than the 1 MB L2 of the machines we measure on).

The ball is a UV sphere (`segments` around, `segments / 2` from pole to
pole: 2 x segments^2 / 2 triangles, minus the poles' degenerate halves),
its radius modulated by smooth bumps so that neighbouring triangles are not
coplanar and the lighting shows the tessellation is right. Built with
numpy, deterministic, no files: the same JSON on every machine.
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

NAME = "cornell-mesh"


def bumpy_ball(segments: int = 320, center=(-0.33, -0.58, -0.28), radius: float = 0.38,
               bump: float = 0.06) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (n, 3), faces (m, 3)) of the ball, faces wound outwards."""
    n_theta = segments // 2  # rings from the north pole (theta 0) to the south pole
    theta = np.linspace(0.0, np.pi, n_theta + 1)
    phi = np.linspace(0.0, 2.0 * np.pi, segments, endpoint=False)
    th, ph = np.meshgrid(theta[1:-1], phi, indexing="ij")  # the rings without the poles
    r = radius * (1.0 + bump * np.sin(5.0 * th) * np.sin(7.0 * ph)
                  + 0.5 * bump * np.sin(11.0 * th + 1.0) * np.cos(13.0 * ph))
    ring = np.stack([r * np.sin(th) * np.cos(ph), r * np.cos(th), r * np.sin(th) * np.sin(ph)],
                    axis=-1).reshape(-1, 3)
    north = np.array([[0.0, radius, 0.0]])
    south = np.array([[0.0, -radius, 0.0]])
    vertices = np.concatenate([north, ring, south]) + np.asarray(center)
    rings = n_theta - 1

    def at(i, j):  # vertex index of ring i (0 = nearest the north pole), column j
        return 1 + i * segments + (j % segments)

    faces = []
    j = np.arange(segments)
    faces.append(np.stack([np.zeros(segments, int), at(0, j + 1), at(0, j)], axis=1))
    for i in range(rings - 1):
        a, b, c, d = at(i, j), at(i, j + 1), at(i + 1, j), at(i + 1, j + 1)
        faces.append(np.stack([a, b, c], axis=1))
        faces.append(np.stack([b, d, c], axis=1))
    last = len(vertices) - 1
    faces.append(np.stack([np.full(segments, last), at(rings - 1, j), at(rings - 1, j + 1)], axis=1))
    return vertices, np.concatenate(faces)


def scene_doc(segments: int = 320) -> dict:
    """cornell-box's document with the large box replaced by the ball."""
    from renderer.scene_format import _load_builtin

    doc = copy.deepcopy(_load_builtin("cornell-box"))
    vertices, faces = bumpy_ball(segments)
    doc["name"] = NAME
    doc["description"] = (f"cornell-box with a bumpy ball of {len(faces)} triangles in place of "
                          "the tall box (bench/heavy_mesh.py)")
    doc["shapes"] = [s for s in doc["shapes"] if s.get("name") != "large-box"]
    doc["shapes"].append({"name": "ball", "type": "mesh", "material": "white",
                          "vertices": np.round(vertices, 9).tolist(), "faces": faces.tolist()})
    return doc


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--segments", type=int, default=320)
    parser.add_argument("--out", required=True)
    args = parser.parse_args(argv)
    doc = scene_doc(args.segments)
    Path(args.out).write_text(json.dumps(doc))
    print(f"{args.out}: {len(doc['shapes'][-1]['faces'])} triangles in the ball")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
