"""Target bodies that ship with minretarget: T-pose meshes made with anny (Apache-2.0 code, CC0
MakeHuman assets), canonical metres, +Y up, facing +Z; ``minretarget bodies`` lists them and
a TARGET may name one (``minretarget retarget walk.bvh heavy_woman``).

``data/bodies.npz`` (written by ``python -m training.data bodies``): names (B,), vertices
(B, V, 3) float32, faces (F, 3) uint16 (one topology for all), phenotypes () JSON {name:
anny phenotype}, licence () str. ``python -m training.data body`` makes other ones.
"""
import json
from pathlib import Path

import numpy as np

BODIES = Path(__file__).parent / "data" / "bodies.npz"


def body_names(path=BODIES):
    """The shipped bodies' names, in the file's order."""
    with np.load(path, allow_pickle=False) as data:
        return tuple(str(name) for name in data["names"])


def shipped_body(name, path=BODIES):
    """A shipped body: (V, 3) float32 T-pose vertices, canonical metres, and (F, 3) int64
    faces; ValueError naming the bodies there are."""
    names = body_names(path)
    if name not in names:
        raise ValueError(f"{name}: no such file, nor a shipped body ({', '.join(names)})")
    with np.load(path, allow_pickle=False) as data:
        return (data["vertices"][names.index(name)].astype(np.float32),
                data["faces"].astype(np.int64))


def body_lines(path=BODIES):
    """``minretarget bodies``: a line per body, its name, height and anny phenotype."""
    with np.load(path, allow_pickle=False) as data:
        phenotypes = json.loads(str(data["phenotypes"]))
        heights = np.ptp(data["vertices"][..., 1], axis=1)                       # (B,)
        return [f"{name:15} {height:.2f} m  (anny: " + ", ".join(
                    f"{label} {value:g}" for label, value in phenotypes[name].items()
                    if label in ("gender", "age", "weight", "height", "muscle")) + ")"
                for name, height in zip(body_names(path), heights)]
