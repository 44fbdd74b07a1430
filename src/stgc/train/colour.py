"""Per-training-camera colour correction: what a real rig's cameras disagree on, learned beside the model.

Real multi-camera rigs differ in exposure and white balance from camera to camera. Without a correction the model
spends Gaussians and view-dependent colour on reproducing each camera's own tint, which no held-out camera shares.
Dynamic 3D Gaussians learns, on the Panoptic captures, an affine map per camera and channel applied to the render
before the loss: exp(m) * render + c. stgc does the same for the training cameras only:

- Views never trained on (the test cameras, orbit views) are rendered without any correction: the model's own
  colour, which is that of the *average* training camera, because after every step the log gains and offsets
  are re-centred to mean zero over the cameras (the product model x correction is otherwise only known up to one
  shared affine map, and the mean camera is the best guess for a camera never seen).
- Only the rows of the cameras in the current batch change (a lazily updated Adam, `torch.optim.SparseAdam`):
  a camera seen in 1 iteration of 15 should not drift on momentum in the other 14.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from stgc.errors import FormatError
from stgc.fileio import read_json_object

# Saved beside point_cloud.ply: the training cameras' learned colour correction (never applied to other views).
COLOUR_CORRECTION_NAME = "colour_correction.json"


class ColourCorrection:
    """exp(log_gain[camera]) * rgb + offset[camera], one gain and offset per training camera and channel."""

    def __init__(self, camera_names: Sequence[str], lr: float):
        self.names = [str(n) for n in camera_names]
        if len(set(self.names)) != len(self.names):
            raise ValueError("camera names must be unique")
        self._index = {n: i for i, n in enumerate(self.names)}
        # Columns 0-2: log gain per channel, 3-5: offset per channel; zero = identity.
        self.table = nn.Embedding(len(self.names), 6, sparse=True)
        nn.init.zeros_(self.table.weight)
        self.lr = lr
        self.optimizer = torch.optim.SparseAdam(self.table.parameters(), lr=lr, eps=1e-15)

    def __contains__(self, name: str) -> bool:
        return str(name) in self._index

    def apply(self, rgb: torch.Tensor, camera_name: str) -> torch.Tensor:
        """The corrected render [H, W, 3] of a training camera (differentiable in both)."""
        row = self.table(torch.tensor([self._index[str(camera_name)]]))[0]
        return rgb * torch.exp(row[:3]) + row[3:]

    def scale_learning_rate(self, scale: float) -> None:
        """This run's configured rate times `scale` (the rate-aware window's lr_scale; 1 outside it)."""
        for group in self.optimizer.param_groups:
            group["lr"] = self.lr * scale

    def step(self) -> None:
        """One Adam step on the rows that received gradients, then re-centre the gauge."""
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)
        with torch.no_grad():
            self.table.weight -= self.table.weight.mean(dim=0, keepdim=True)

    def gains(self) -> torch.Tensor:
        return torch.exp(self.table.weight.detach()[:, :3])

    def offsets(self) -> torch.Tensor:
        return self.table.weight.detach()[:, 3:].clone()

    def as_dict(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """{camera: (gain [3], offset [3])}, the form `saved_corrections` reads back."""
        gains, offsets = self.gains().numpy(), self.offsets().numpy()
        return {n: (gains[i], offsets[i]) for i, n in enumerate(self.names)}

    def to_json(self) -> dict[str, Any]:
        gains, offsets = self.gains(), self.offsets()
        return {
            "model": "rgb * gain + offset per training camera and channel; identity for every other view",
            "cameras": {n: {"gain": [round(float(g), 6) for g in gains[i]],
                            "offset": [round(float(c), 6) for c in offsets[i]]}
                        for i, n in enumerate(self.names)},
            "summary": self.summary(),
        }

    def summary(self) -> dict[str, float]:
        gains = self.gains()
        return {
            "gain_min": round(float(gains.min()), 4),
            "gain_max": round(float(gains.max()), 4),
            "gain_std": round(float(gains.std()), 4) if gains.numel() > 1 else 0.0,
            "offset_abs_max": round(float(self.offsets().abs().max()), 4),
        }

    def state_dict(self) -> dict[str, Any]:
        return {"names": list(self.names), "table": self.table.weight.detach().clone(),
                "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        if list(state["names"]) != self.names:
            raise ValueError("the checkpoint's colour correction was trained on other cameras")
        with torch.no_grad():
            self.table.weight.copy_(state["table"])
        self.optimizer.load_state_dict(state["optimizer"])
        # The optimizer's saved state carries the rate it was trained with; a continuation may set another.
        self.scale_learning_rate(1.0)


def saved_corrections(path: Path) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """{camera: (gain [3], offset [3])} from a saved colour_correction.json; {} when the file does not exist (a model
    trained without correction, or a synthetic scene). A file that exists but cannot be read is a FormatError."""
    if not path.is_file():
        return {}
    saved = read_json_object(path)
    try:
        return {str(name): (np.asarray(entry["gain"], np.float32).reshape(3),
                            np.asarray(entry["offset"], np.float32).reshape(3))
                for name, entry in (saved or {})["cameras"].items()}
    except (KeyError, TypeError, ValueError):
        raise FormatError(path, "not a colour correction file (cameras: {name: {gain, offset}})") from None
