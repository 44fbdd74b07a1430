"""Keeping Adam's per-row state aligned with a parameter whose rows are removed, appended or replaced.

Every Gaussian attribute lives in its own Adam group with a single parameter (as in 3DGS/STG). When the rows
change, the Parameter object is replaced; its state entry (exp_avg, exp_avg_sq, and the shared step count) must move
to the new object with the same row edits, otherwise Adam would apply another Gaussian's momentum.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn


def replace_group_param(
    optimizer: torch.optim.Optimizer,
    old: nn.Parameter,
    new: nn.Parameter,
    edit_rows: Callable[[torch.Tensor], torch.Tensor] | None,
) -> None:
    """Swap `old` for `new` in the optimizer, editing per-row state tensors with `edit_rows`.

    edit_rows maps an old state tensor of old's shape to one of new's shape; None resets the moments to zero.
    Scalar state (Adam's `step`) is carried over unchanged.
    """
    for group in optimizer.param_groups:
        for i, param in enumerate(group["params"]):
            if param is old:
                group["params"][i] = new
                break
        else:
            continue
        break
    else:
        raise KeyError("parameter is not managed by this optimizer")
    state = optimizer.state.pop(old, None)
    if not state:
        return  # no step taken yet: Adam creates fresh state lazily
    new_state = {}
    for key, value in state.items():
        if torch.is_tensor(value) and value.shape == old.shape:
            new_state[key] = torch.zeros_like(new) if edit_rows is None else edit_rows(value).contiguous()
        else:
            new_state[key] = value
    optimizer.state[new] = new_state
