"""Build the small demo scene shipped in demo/toys_small from ../shared/data/blender_toys.

Kept: the held-out test camera cam00, every other training camera (8 of 15), every 3rd frame (10 of 30),
and 3,000 surface samples per kept frame. The layout stays the D-NeRF/Blender one (transforms_*.json with
per-frame time and a camera key, camXX/NNNN.png, points3d/NNNN.npy), so the demo exercises a real reader.

    python demo/make_scene.py [SOURCE] [DEST]
"""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
SOURCE = HERE.parent.parent / "shared" / "data" / "blender_toys"
DEST = HERE / "toys_small"
TRAIN_CAMERAS = [f"cam{i:02d}" for i in range(1, 16, 2)]
TEST_CAMERAS = ["cam00"]
FRAME_STEP = 3
POINTS_PER_FRAME = 3000


def main(source: Path = SOURCE, dest: Path = DEST) -> None:
    if dest.exists():
        shutil.rmtree(dest)
    dest.mkdir(parents=True)
    rng = np.random.default_rng(0)
    kept_frames = list(range(0, 30, FRAME_STEP))
    new_index = {old: new for new, old in enumerate(kept_frames)}
    last = len(kept_frames) - 1
    for split, cams in (("train", TRAIN_CAMERAS), ("test", TEST_CAMERAS)):
        meta = json.loads((source / f"transforms_{split}.json").read_text())
        frames = []
        for fr in meta["frames"]:
            if fr["camera"] not in cams or fr["frame_index"] not in new_index:
                continue
            i = new_index[fr["frame_index"]]
            (dest / fr["camera"]).mkdir(exist_ok=True)
            shutil.copyfile(source / fr["camera"] / f"{fr['frame_index']:04d}.png", dest / fr["camera"] / f"{i:04d}.png")
            frames.append({**fr, "file_path": f"./{fr['camera']}/{i:04d}", "frame_index": i, "time": i / last})
        meta.update(frames=frames, num_frames=len(kept_frames), fps=30 // FRAME_STEP)
        (dest / f"transforms_{split}.json").write_text(json.dumps(meta, indent=1))
    (dest / "points3d").mkdir()
    for old, new in new_index.items():
        pts = np.load(source / "points3d" / f"{old:04d}.npy")
        keep = rng.choice(len(pts), size=min(POINTS_PER_FRAME, len(pts)), replace=False)
        np.save(dest / "points3d" / f"{new:04d}.npy", pts[np.sort(keep)])
    (dest / "README.md").write_text(
        "Reduced copy of the blender_toys scene (Blender Cycles render, see ../make_scene.py):\n"
        f"test camera {TEST_CAMERAS[0]}, train cameras {', '.join(TRAIN_CAMERAS)}; frames 0,3,...,27 of the\n"
        f"original renumbered 0..{last} ({30 // FRAME_STEP} fps); {POINTS_PER_FRAME} surface samples per frame.\n"
    )


if __name__ == "__main__":
    main(*(Path(a) for a in sys.argv[1:3]))
