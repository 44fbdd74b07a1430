"""Adaptive density control of Spacetime Gaussians: gradient statistics, clone/split, pruning, opacity reset.

Follows the official STG (`GS/scene/oursfull.py` densify_and_clone / densify_and_split, `helper_train.controlgaussians`),
which is 3DGS density control plus one change: every new Gaussian gets a fresh temporal centre mu_t ~ U[0, 1].
All row edits go through `model.prune` / `model.extend`, which keep Adam's moments aligned; the per-Gaussian
statistics (`DensificationStats`) are edited here with the same masks. `DensityControl` is the whole of it as one
strategy object that the trainer calls around its step.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
import torch

from stgc.data.cameras import Camera
from stgc.errors import StgcError
from stgc.model import STGModel
from stgc.render.projection import quat_to_rotmat
from stgc.train.config import DensifyConfig, FloaterConfig, Schedule

log = logging.getLogger(__name__)

# The most Gaussians one optimizer step may make non-finite, as a share of the model, before the run stops as
# diverged instead of removing them. A lone Adam blow-up hits one row or a few (one row is always tolerated, so that
# a small model may lose one); a NaN or inf gradient from anything rows share (a culled row's temporal opacity was
# one: every row with trbf_scale below about -44, at every step; a decoder, background or colour-correction gradient
# goes to every row a view reached) hits tens of percent. Removing more than 1 % of the model in one step is losing
# the model, not cleaning it.
NONFINITE_DIVERGED_SHARE = 0.01


def reaches_view(model: STGModel, camera: Camera, t: float) -> torch.Tensor:
    """[N] bool: the Gaussians in front of the camera's near plane whose 3-sigma box (3 x the largest scale) at
    time t overlaps the image: where the official rasterizer gives a positive radius, whatever the opacity."""
    with torch.no_grad():
        means = model.means_at(t).double()
        w2c = torch.as_tensor(np.asarray(camera.w2c), dtype=torch.float64)
        K = torch.as_tensor(np.asarray(camera.K), dtype=torch.float64)
        cam = means @ w2c[:3, :3].T + w2c[:3, 3]
        z = cam[:, 2]
        ahead = z > float(camera.near)
        depth = torch.where(ahead, z, torch.ones_like(z))
        u = K[0, 0] * cam[:, 0] / depth + K[0, 2]
        v = K[1, 1] * cam[:, 1] / depth + K[1, 2]
        sigma = torch.exp(model.params["scaling"].detach().double()).amax(dim=1)
        radius = 3.0 * sigma * torch.maximum(K[0, 0], K[1, 1]) / depth
        inside = (u + radius > 0) & (u - radius < camera.width) & (v + radius > 0) & (v - radius < camera.height)
    return ahead & inside


class DensificationStats:
    """Per-Gaussian sum of NDC screen-space mean-gradient norms and the number of views that saw it."""

    def __init__(self, num_gaussians: int):
        self.grad_sum: torch.Tensor
        self.count: torch.Tensor
        self.reset(num_gaussians)

    def __len__(self) -> int:
        return self.grad_sum.shape[0]

    def add(self, index: torch.Tensor, grad_norm: torch.Tensor, visible: torch.Tensor) -> None:
        """Accumulate one view: `index` maps the rasterized subset to model rows; only visible ones count."""
        rows = index[visible]
        self.grad_sum.index_add_(0, rows, grad_norm[visible].detach().to(torch.float64))
        self.count.index_add_(0, rows, torch.ones_like(rows))

    def mean_grad(self) -> torch.Tensor:
        return torch.where(self.count > 0, self.grad_sum / self.count.clamp(min=1), torch.zeros_like(self.grad_sum))

    def keep(self, mask: torch.Tensor) -> None:
        mask = torch.as_tensor(mask, dtype=torch.bool).to(self.grad_sum.device)
        self.grad_sum, self.count = self.grad_sum[mask], self.count[mask]

    def reset(self, num_gaussians: int) -> None:
        self.grad_sum = torch.zeros(num_gaussians, dtype=torch.float64)
        self.count = torch.zeros(num_gaussians, dtype=torch.int64)

    def state_dict(self) -> dict[str, torch.Tensor]:
        return {"grad_sum": self.grad_sum.clone(), "count": self.count.clone()}

    def load_state_dict(self, state: dict[str, torch.Tensor]) -> None:
        self.grad_sum, self.count = state["grad_sum"].clone(), state["count"].clone()


def _rows(model: STGModel, mask: torch.Tensor) -> dict[str, torch.Tensor]:
    return {k: p.detach()[mask].clone() for k, p in model.params.items()}


@torch.no_grad()
def clone_and_split(
    model: STGModel,
    stats: DensificationStats,
    grad_threshold: float,
    percent_dense: float,
    split_count: int,
    generator: torch.Generator,
    max_gaussians: int = 0,
) -> dict[str, int]:
    """One official densification round. Returns counts {"cloned", "split"}; `stats` is reset afterwards.

    Clone: small Gaussians (max scale <= percent_dense * E) with a large mean gradient are copied exactly, except
    mu_t ~ U[0,1]. Split: large ones are replaced by `split_count` Gaussians whose positions are drawn from the
    original Gaussian, scales divided by 0.8 * split_count, mu_t ~ U[0,1].
    """
    n0 = model.num_gaussians
    grads = stats.mean_grad().to(torch.float32)
    max_scale = model.scales.detach().max(dim=1).values
    size_limit = percent_dense * model.scene_extent
    high = grads >= grad_threshold
    large = max_scale > size_limit
    if max_gaussians > 0:
        high = _within_budget(high, grads, large, split_count, max_gaussians - n0)
    clone_mask = high & ~large
    split_mask = high & large
    n_clone, n_split = int(clone_mask.sum()), int(split_mask.sum())

    new_parts: list[dict[str, torch.Tensor]] = []
    if n_clone:
        clones = _rows(model, clone_mask)
        clones["trbf_center"] = torch.rand(n_clone, 1, generator=generator, dtype=clones["trbf_center"].dtype)
        new_parts.append(clones)
    if n_split:
        base = _rows(model, split_mask)
        stds = torch.exp(base["scaling"]).repeat(split_count, 1)
        samples = torch.randn(stds.shape, generator=generator, dtype=stds.dtype) * stds
        rot = quat_to_rotmat(base["rotation"]).repeat(split_count, 1, 1)
        split = {k: v.repeat(split_count, *([1] * (v.ndim - 1))) for k, v in base.items()}
        split["xyz"] = torch.bmm(rot, samples.unsqueeze(-1)).squeeze(-1) + split["xyz"]
        split["scaling"] = torch.log(stds / (0.8 * split_count))
        split["trbf_center"] = torch.rand(
            n_split * split_count, 1, generator=generator, dtype=split["trbf_center"].dtype
        )
        new_parts.append(split)
    if new_parts:
        new = {k: torch.cat([part[k] for part in new_parts]) for k in model.params}
        model.extend(new)
    if n_split:
        # The split originals go; clones and split children (appended at the end) stay.
        keep = torch.ones(model.num_gaussians, dtype=torch.bool)
        keep[:n0] = ~split_mask
        model.prune(keep)
    stats.reset(model.num_gaussians)
    return {"cloned": n_clone, "split": n_split}


def _within_budget(candidates: torch.Tensor, grads: torch.Tensor, is_split: torch.Tensor, split_count: int,
                   room: int) -> torch.Tensor:
    """The candidates, largest gradient first, whose added Gaussians (1 per clone, split_count - 1 per split) fit
    in `room`."""
    order = torch.argsort(grads.masked_fill(~candidates, -1.0), descending=True)[: int(candidates.sum())]
    added = torch.where(is_split[order], split_count - 1, 1).cumsum(0)
    keep = torch.zeros_like(candidates)
    keep[order[added <= max(room, 0)]] = True
    return keep


@torch.no_grad()
def prune_mask_low_opacity(model: STGModel, threshold: float) -> torch.Tensor:
    """Rows to REMOVE: opacity sigmoid(o) below `threshold`."""
    return torch.sigmoid(model.params["opacity"].detach()).squeeze(-1) < threshold


@torch.no_grad()
def prune_mask_nonfinite(model: STGModel) -> torch.Tensor:
    """Rows to REMOVE: any parameter is NaN or infinite (rare Adam blow-ups; harmless to drop)."""
    bad = torch.zeros(model.num_gaussians, dtype=torch.bool)
    # Every training step asks, and nearly always nothing is: a NaN or inf anywhere makes its tensor's sum
    # non-finite (and a finite sum that overflows only takes the exact path), at a ninth of the exact scan's time
    # (1.5 against 13.8 ms at 35k Gaussians, one thread).
    if all(bool(torch.isfinite(p.detach().sum())) for p in model.params.values()):
        return bad
    for p in model.params.values():
        finite = torch.isfinite(p.detach())
        bad |= ~(finite.flatten(1).all(dim=1) if p.ndim > 1 else finite)  # (reshape(N, -1) failed for N = 0)
    return bad


@torch.no_grad()
def nonfinite_groups(model: STGModel, rows: torch.Tensor) -> dict[str, int]:
    """{parameter group: how many of the rows `rows` (a bool mask) have a NaN or infinite value in it}, the groups
    with none left out."""
    counts = {}
    for key, p in model.params.items():
        finite = torch.isfinite(p.detach())
        bad = ~(finite.flatten(1).all(dim=1) if p.ndim > 1 else finite)
        count = int((bad & rows).sum())
        if count:
            counts[key] = count
    return counts


def describe_nonfinite(model: STGModel, rows: torch.Tensor, shown: int = 8) -> str:
    """'3 of 180 Gaussians (rows 0, 1, 2; non-finite in xyz: 3, trbf_scale: 1)': for messages."""
    index = torch.nonzero(rows, as_tuple=False)[:, 0].tolist()
    listed = ", ".join(str(i) for i in index[:shown])
    if len(index) > shown:
        listed += f", ... ({len(index) - shown} more)"
    groups = ", ".join(f"{key}: {n}" for key, n in nonfinite_groups(model, rows).items())
    return f"{len(index)} of {model.num_gaussians} Gaussians (row{'s' if len(index) != 1 else ''} {listed}; " \
           f"non-finite in {groups})"


@torch.no_grad()
def prune_mask_floaters(
    model: STGModel, camera_centers: np.ndarray, near_camera: float, max_world_scale: float,
    scale_min_opacity: float = 0.0,
) -> torch.Tensor:
    """Rows to REMOVE by the floater rules (0 disables a rule).

    near_camera: the Gaussian's centre (its position at its own temporal centre) lies within near_camera * E of a
    training camera centre (E: the scene extent); such Gaussians cover held-out views with blur although training
    views barely see them.
    max_world_scale: its largest axis exceeds max_world_scale * `scene_radius`. A Gaussian larger than the scene
    sits mostly behind what the training views see, where they cannot correct it, and a held-out camera that looks
    past the modelled surfaces sees it as a haze over the whole image.
    scale_min_opacity: the scale rule only removes Gaussians at least this opaque (base opacity): a haze needs
    opacity, and large translucent needles and sheets inside the scene do real work for some views (0 = any).
    """
    remove = torch.zeros(model.num_gaussians, dtype=torch.bool)
    extent = model.scene_extent
    xyz = model.params["xyz"].detach()
    centers = torch.as_tensor(np.asarray(camera_centers, dtype=np.float64).reshape(-1, 3), dtype=xyz.dtype)
    if near_camera > 0 and len(centers):
        nearest = torch.cdist(xyz, centers).min(dim=1).values
        remove |= nearest < near_camera * extent
    if max_world_scale > 0 and model.num_gaussians:
        large = model.scales.detach().max(dim=1).values > max_world_scale * scene_radius(model, centers)
        remove |= large & (model.opacity.detach() >= scale_min_opacity)
    return remove


def scene_radius(model: STGModel, camera_centers: torch.Tensor) -> float:
    """How far the scene reaches from the training cameras' centroid: the 99th percentile of the Gaussian centres'
    distances from it, and at least the scene extent E (cameras around a scene: E; a forward-facing rig, whose
    background lies far beyond its cameras: the background's distance)."""
    xyz = model.params["xyz"].detach()
    if not len(camera_centers) or not len(xyz):
        return float(model.scene_extent)
    distances = (xyz - camera_centers.mean(dim=0)).norm(dim=1)
    finite = distances[torch.isfinite(distances)]
    reach = float(torch.quantile(finite, 0.99)) if len(finite) else 0.0
    return max(float(model.scene_extent), reach)


def apply_prune(model: STGModel, stats: DensificationStats, remove: torch.Tensor) -> int:
    """Remove rows from the model (and its Adam state) and from the trainer statistics; returns how many."""
    n = int(remove.sum())
    if n:
        keep = ~remove
        model.prune(keep)
        stats.keep(keep)
    return n


class DensityControl:
    """The official density control as a strategy around the training step (in the manner of gsplat's
    `Strategy`): it watches each view's render for the screen-space gradient statistics (`observe`), and after the
    optimizer step clones/splits, prunes and resets opacities when the schedule says so (`step`). Gaussians that
    others remove (compaction, the learned mask) are reported to it (`rows_kept`), so its statistics stay aligned with
    the model's rows, and a capped schedule's cap drops by as many: clone/split does not refill what compaction
    removed (a sparse cloud's rounds run into the ST-KNN window, and refilling to the cap undid its first steps);
    when others add some (EMS) every statistic starts again (`restart_statistics`), as officially. Its state goes
    into the training checkpoint under the keys it always had."""

    def __init__(self, cfg: DensifyConfig, floaters: FloaterConfig, schedule: Schedule, initial_gaussians: int,
                 train_centers: np.ndarray):
        self.cfg, self.floaters, self.schedule = cfg, floaters, schedule
        self.train_centers = train_centers
        self.stats = DensificationStats(initial_gaussians)
        self.initial_gaussians = initial_gaussians
        self.rounds_done = 0
        self.past_rounds = False  # a densification step after the schedule's last round has passed
        self.removed_by_others = 0  # Gaussians compaction removed: they lower the cap
        self.rows_fixed = False  # set while the learned mask keeps one logit per row: no removal between rounds
        self.pruned_nonfinite = 0  # Gaussians removed for non-finite parameters in the whole run (a resume too)

    @property
    def collecting(self) -> bool:
        """Whether clone/split rounds are still ahead (the statistics only matter until then): rounds owed, and the
        schedule's last round not passed (a continuation that owes rounds clones no more)."""
        return self.rounds_done < self.schedule.densify_rounds and not self.past_rounds

    def observe(self, render: Any, view_index: int, batch: int, model: STGModel | None = None,
                camera: Camera | None = None, t: float = 0.0) -> None:
        """After the backward of a `batch`-view step (one backward of the views' summed loss): add view
        `view_index`'s screen-space gradients. With `stats_count` 'in_frustum' (needs `model`, `camera` and the view's
        time `t`), the Gaussians the render culled as temporally invisible count the view too, where their 3-sigma box
        reaches it."""
        if not self.collecting or (self.cfg.stats_views == "last" and view_index != batch - 1):
            return
        # Each view's screen-space gradient is its own (a render's means2d is its own tensor); it came from
        # loss/batch, hence the factor batch to get the per-view gradient.
        grad_norm = render.raster.means2d_grad_ndc_norm() * batch
        self.stats.add(render.index, grad_norm, render.raster.visible)
        if self.cfg.stats_count == "in_frustum":
            if model is None or camera is None:
                raise ValueError("densify.stats_count 'in_frustum' needs the model, camera and time of the view")
            culled = torch.ones(model.num_gaussians, dtype=torch.bool)
            culled[render.index] = False
            rows = torch.nonzero(culled & reaches_view(model, camera, t), as_tuple=False)[:, 0]
            self.stats.count.index_add_(0, rows, torch.ones_like(rows))

    def step(self, iteration: int, model: STGModel, generator: torch.Generator) -> dict[str, int]:
        """After the optimizer step: what the schedule asks at `iteration`; returns what it did (counts)."""
        sched, d, fl = self.schedule, self.cfg, self.floaters
        report: dict[str, int] = {}
        nonfinite = prune_mask_nonfinite(model)
        if bool(nonfinite.any()):
            self._check_nonfinite(iteration, model, nonfinite, sched.is_densify_step(iteration))
        if sched.is_densify_step(iteration):
            # Rounds are the schedule's up to its last (densify_end), as check_rate_aware_window and config.json say: a
            # continuation past it that owes rounds (densification switched on, more rounds) clones no more.
            self.past_rounds = self.past_rounds or iteration > sched.densify_end
            if self.collecting:
                report.update(clone_and_split(model, self.stats, d.grad_threshold, d.percent_dense, d.split_count,
                                              generator, max_gaussians=self.cap()))
                self.rounds_done += 1
                if d.prune_in_rounds:
                    report["pruned_opacity"] = apply_prune(model, self.stats,
                                                           prune_mask_low_opacity(model, d.prune_opacity))
            elif iteration < sched.prune_until:
                report["pruned_opacity"] = apply_prune(model, self.stats, prune_mask_low_opacity(model, d.prune_opacity))
            if iteration <= sched.floaters_until and (fl.near_camera > 0 or fl.max_world_scale > 0):
                remove = prune_mask_floaters(model, self.train_centers, fl.near_camera, fl.max_world_scale,
                                             fl.scale_min_opacity)
                report["pruned_floaters"] = apply_prune(model, self.stats, remove)
            # (Clone/split copied any non-finite row it picked: the mask again.)
            report["pruned_nonfinite"] = self._prune_nonfinite(iteration, model, prune_mask_nonfinite(model))
        elif not self.rows_fixed and bool(nonfinite.any()):
            # Between rounds too: a visible row that an optimizer step made non-finite stops the next render, and
            # one the render culls stops the next save (a resume replays to the same stop). With the learned mask
            # (rows_fixed) the row stays: the rate-aware window's quantization stops the next step, naming it.
            report["pruned_nonfinite"] = self._prune_nonfinite(iteration, model, nonfinite)
        if sched.is_opacity_reset(iteration):
            model.reset_opacity(d.opacity_reset_value)
            report["opacity_reset"] = 1
        return report

    def _check_nonfinite(self, iteration: int, model: STGModel, nonfinite: torch.Tensor, densify_step: bool) -> None:
        """Stop the run where removing the rows the optimizer step of `iteration` made non-finite would be wrong:
        inside the learned mask's window (a densification step would remove them, and the mask keep their logits),
        or when they are more than NONFINITE_DIVERGED_SHARE of the model (the training diverged)."""
        count, total = int(nonfinite.sum()), model.num_gaussians
        if self.rows_fixed:
            if densify_step:
                raise StgcError(
                    f"training diverged at iteration {iteration}, inside the rate-aware window's learned mask: the "
                    f"optimizer step made {describe_nonfinite(model, nonfinite)} non-finite although the loss was "
                    "finite, and the mask keeps one logit per Gaussian, so none can be removed; lower the learning "
                    "rates of those parameters (train.lr) or train.quantization_aware.mask_lr / rate_weight and train "
                    "(or fine-tune) again")
            return
        if count > max(1, NONFINITE_DIVERGED_SHARE * total):
            raise StgcError(
                f"training diverged at iteration {iteration}: the optimizer step made "
                f"{describe_nonfinite(model, nonfinite)} non-finite although the loss was finite (a NaN or inf "
                f"gradient); removing more than {NONFINITE_DIVERGED_SHARE:.0%} of the model in one step would lose it "
                "silently; lower the learning rates of those parameters (train.lr) and train again")

    def _prune_nonfinite(self, iteration: int, model: STGModel, remove: torch.Tensor) -> int:
        """Remove the non-finite rows `remove`, with a warning; returns how many."""
        if not bool(remove.any()):
            return 0
        what = describe_nonfinite(model, remove)
        n = apply_prune(model, self.stats, remove)
        self.pruned_nonfinite += n
        log.warning("iteration %d: removed %s: an optimizer step made them non-finite (%d removed so far in this run)",
                    iteration, what, self.pruned_nonfinite)
        return n

    def restart_statistics(self, num_gaussians: int) -> None:
        """Every row's gradient statistic from zero (what the official code does whenever it adds Gaussians)."""
        self.stats.reset(num_gaussians)

    def cap(self) -> int:
        """The count clone/split may not exceed now (0 = none): the configured cap less what others removed."""
        cap = self.cfg.cap(self.initial_gaussians)
        return max(cap - self.removed_by_others, 1) if cap else 0

    def rows_kept(self, keep: torch.Tensor) -> None:
        self.removed_by_others += int((~torch.as_tensor(keep, dtype=torch.bool)).sum())
        self.stats.keep(keep)

    def state_dict(self) -> dict[str, Any]:
        return {"densify_stats": self.stats.state_dict(), "densify_rounds_done": self.rounds_done,
                "initial_gaussians": self.initial_gaussians, "densify_past_rounds": self.past_rounds,
                "densify_removed_by_others": self.removed_by_others, "densify_pruned_nonfinite": self.pruned_nonfinite}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.stats.load_state_dict(state["densify_stats"])
        self.rounds_done = int(state["densify_rounds_done"])
        # Checkpoints written before the Gaussian budget existed have no count: keep the model's own.
        self.initial_gaussians = int(state.get("initial_gaussians", self.initial_gaussians))
        self.past_rounds = bool(state.get("densify_past_rounds", False))  # (checkpoints from before session 29)
        self.removed_by_others = int(state.get("densify_removed_by_others", 0))  # (before session 30)
        self.pruned_nonfinite = int(state.get("densify_pruned_nonfinite", 0))  # (checkpoints before this count)
