"""Mocap point labeler: per-frame self-attention + Sinkhorn with dustbins (paper 003 §4.1-4.2, §4.5).

One frame is an unordered set of N points (real markers, ghost points and padding slots,
see :class:`~unibody.mocap.corrupt.MocapBatch`); the labeler gives each real point one of L
marker labels or the null label L:

1. centre each frame on the per-axis median of its real points (paper §4.1) or on the
   middle of their 5-95 % range (``centre="midrange"``);
2. per-point features: a pointwise MLP, 3 -> width;
3. ``layers`` pre-LayerNorm transformer blocks: multi-head self-attention over the frame's
   real points (padding never serves as a key) and a feed-forward layer, both residual;
4. a score head, width -> L, gives scores S (B, N, L);
5. :func:`~unibody.mocap.sinkhorn.log_sinkhorn` with one learnable dustbin score
   (initialised to 1) gives the log plan (B, N+1, L+1).

Points are in the unibody frame (metres, Y up). The network has no notion of heading:
invariance to rotations about the vertical axis comes from training data only (the
synthetic generator draws a uniform heading), as in the paper. It is permutation
equivariant, so the order of the points does not matter.

Two stages (our addition): a labeler may carry an ``orienter``, a labeler trained on frames
in every orientation. Each frame is labelled by the orienter first, rotated into the layout's
rest frame by a rigid fit of its torso markers (:mod:`unibody.mocap.orient`) and centred on
the points the orienter called markers; this labeler, trained on frames oriented the same
way, then labels it with up, left and front as fixed axes. Lying, tumbling and leaning
bodies gain most. When the orienter mislabels the torso (mostly lying and inverted frames),
the frame is turned the wrong way and this labeler is unsure of its labels: with ``retry``,
such frames are oriented again from the orienter's labels of the frame tipped over in 13
ways (:data:`~unibody.mocap.orient.TILTS`), then from this labeler's own best labels and
small turns of that orientation (:data:`~unibody.mocap.orient.NUDGES`), and keep the labels
this labeler is surest of.

Differences from the paper's network (1.44 M parameters, d=125, 8 layers, 5 heads,
BatchNorm, post-merge MLP): LayerNorm instead of BatchNorm (no train/eval difference, no
batch statistics over padding) and a smaller default size so that labelling runs at
thousands of frames per second on two CPU threads.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import torch
from torch import nn

from .._checks import check_finite, check_like, check_shape
from ..geometry.rotations import rotation_angle
from ..io.atomic import atomic_path
from ..io.weights import read_weights, rebuilding
from .orient import NUDGES, TILTS, fit_rotation
from .sinkhorn import log_sinkhorn

if TYPE_CHECKING:
    from .corrupt import MocapBatch
    from .tracklets import TrackletConfig

__all__ = [
    "LABELER_FORMAT",
    "FrameLabels",
    "Labeler",
    "LabelerConfig",
    "check_retry",
    "frame_probabilities",
    "label_frames",
    "labeling_loss",
    "predict",
    "sequence_probabilities",
]

LABELER_FORMAT = "unibody.labeler/1"
_NEG_BIAS = -1.0e9  # attention logit of padding keys: softmax weight exactly 0
# Frames per pass. On a 2-core CPU (torch 2.13), 256 real frames labelled in passes of 64-128
# frames ran 10-20 % faster than in one pass of 256, or as fast when the VM was slow; a 377-frame
# pass was slower still (benchmarks/README.md). Frames are independent: the plans are the same.
# A GPU takes the whole batch in one pass.
_CHUNK = 96


class _Block(nn.Module):
    """Pre-LN transformer block: x + MHA(LN(x)), then x + FFN(LN(x))."""

    def __init__(self, width: int, heads: int) -> None:
        super().__init__()
        self.heads = heads
        self.norm1 = nn.LayerNorm(width)
        self.qkv = nn.Linear(width, 3 * width)
        self.proj = nn.Linear(width, width)
        self.norm2 = nn.LayerNorm(width)
        self.ffn = nn.Sequential(nn.Linear(width, 2 * width), nn.ReLU(inplace=True), nn.Linear(2 * width, width))

    def forward(self, x: torch.Tensor, key_bias: torch.Tensor) -> torch.Tensor:
        """x (B, N, W); key_bias (B, 1, 1, N): 0 where a point may be attended to, very negative elsewhere."""
        b, n, w = x.shape
        d = w // self.heads
        # one copy into (3, B, H, N, d), so that both products run as batched GEMMs without copies
        q, k, v = self.qkv(self.norm1(x)).view(b, n, 3, self.heads, d).permute(2, 0, 3, 1, 4).contiguous()
        # Explicit softmax attention: for ~50 points it is several times faster on CPU than
        # F.scaled_dot_product_attention (flash kernel), forward and backward (measured, torch 2.13).
        att = torch.softmax((q @ k.transpose(-1, -2)).mul_(d**-0.5).add_(key_bias), dim=-1) @ v  # (B, H, N, d)
        x = x + self.proj(att.transpose(1, 2).reshape(b, n, w))
        return x + self.ffn(self.norm2(x))


def _check_plain(x: object, name: str) -> None:
    """Require JSON-like data (what ``torch.load(weights_only=True)`` reads back)."""
    if isinstance(x, dict):
        for k, v in x.items():
            if not isinstance(k, str):
                raise TypeError(f"{name}: keys must be str, got {type(k).__name__}")
            _check_plain(v, f"{name}[{k!r}]")
    elif isinstance(x, (list, tuple)):
        for i, v in enumerate(x):
            _check_plain(v, f"{name}[{i}]")
    elif x is not None and type(x) not in (str, int, float, bool):
        raise TypeError(f"{name}: expected str/int/float/bool/None or lists/dicts of them, got {type(x).__name__}")


_ARCHITECTURE = ("num_labels", "width", "layers", "heads")  # fixed by the weights


@dataclass(frozen=True)
class LabelerConfig:
    """The settings of a :class:`Labeler` (saved with its weights as a plain dict, :meth:`to_dict`).

    ``num_labels``, ``width``, ``layers`` and ``heads`` fix the network's shape; the others
    only change how it labels and may differ between two labelers with the same weights
    (:meth:`Labeler.with_config`). The attributes are the :class:`Labeler` arguments of the
    same names.
    """

    num_labels: int
    width: int = 96
    layers: int = 4
    heads: int = 4
    sinkhorn_iters: int = 35
    centre: str = "median"
    refine: int = 0
    retry: float = 0.0

    def __post_init__(self) -> None:
        if self.num_labels < 1:
            raise ValueError(f"num_labels: expected >= 1, got {self.num_labels}")
        if self.width < 1 or self.layers < 0 or self.heads < 1 or self.width % self.heads:
            raise ValueError(
                f"width/heads: expected width divisible by heads, got width={self.width}, heads={self.heads}"
            )
        if self.sinkhorn_iters < 1:
            raise ValueError(f"sinkhorn_iters: expected >= 1, got {self.sinkhorn_iters}")
        if self.centre not in ("median", "midrange"):
            raise ValueError(f"centre: expected 'median' or 'midrange', got {self.centre!r}")
        if self.refine < 0:
            raise ValueError(f"refine: expected >= 0, got {self.refine}")
        check_retry(self.retry, True)  # the range; whether retry needs an orienter is the Labeler's check
        object.__setattr__(self, "retry", float(self.retry))

    def to_dict(self) -> dict:
        """The settings as a plain dict (what the weights file stores)."""
        return asdict(self)

    @classmethod
    def from_dict(cls, config: dict) -> LabelerConfig:
        """Settings from a weights file's dict (absent keys take their defaults, e.g. ``retry`` in older files)."""
        return cls(**config)


class Labeler(nn.Module):
    """Label the points of mocap frames with L marker labels or null.

    Args:
        num_labels: L, the number of marker labels (the null label is L).
        label_names: the L marker names (saved with the weights); ``None`` gives "0", "1", ...
        width: feature width of every point.
        layers: number of self-attention blocks.
        heads: attention heads; must divide ``width``.
        sinkhorn_iters: Sinkhorn iterations (paper: 35).
        centre: how a frame is centred: ``"median"`` of its real points per axis (paper §4.1)
            or ``"midrange"``, the middle of their 5-95 % range per axis (robust to many extra
            markers crowded on one part of the body, e.g. pyCGM's foot markers).
        refine: re-centring passes when labelling (training uses none): the first pass centres
            each frame on the midrange of all its points, each further pass on the ``centre``
            rule applied to the points the last pass labelled as markers. Extra markers or
            ghosts crowded on one part of the body then no longer move the frame's centre.
        orienter: a labeler (without an orienter of its own) whose labels orient every frame,
            in training too; its weights are frozen and saved with these. Its Lo labels are
            these labels or some of them (a session layout's model may orient with the
            general layout's first stage: label priming, paper §4.5).
        template, torso: (Lo, 3) rest-frame positions and (Lo,) bool torso flags of the
            orienter's markers, which its labels are fitted to
            (:func:`~unibody.mocap.orient.torso_template`); needed with ``orienter``.
        retry: with an orienter, frames whose mean label confidence (over their real points)
            is below ``retry`` are oriented again (see above; 0 never, 1 every frame; training
            uses none). The labels kept are those of the orientation with the highest mean
            confidence, so a retried frame is never less sure than it was.

    Attributes:
        config: the :class:`LabelerConfig` (frozen); assign a changed copy
            (``dataclasses.replace(model.config, retry=0.5)``, checked) or use :meth:`with_config`.
        meta: free-form training record (command, seed, steps, metrics), saved with the weights.
    """

    def __init__(
        self,
        num_labels: int,
        *,
        label_names: Sequence[str] | None = None,
        width: int = 96,
        layers: int = 4,
        heads: int = 4,
        sinkhorn_iters: int = 35,
        centre: str = "median",
        refine: int = 0,
        orienter: Labeler | None = None,
        template: torch.Tensor | None = None,
        torso: torch.Tensor | None = None,
        retry: float = 0.0,
    ) -> None:
        super().__init__()
        config = LabelerConfig(num_labels, width, layers, heads, sinkhorn_iters, centre, refine, retry)
        check_retry(retry, orienter is not None)
        names = tuple(str(i) for i in range(num_labels)) if label_names is None else tuple(label_names)
        if len(names) != num_labels:
            raise ValueError(f"label_names: expected {num_labels} names, got {len(names)}")
        self.label_names = names
        self.autocast: torch.dtype | None = None  # set_autocast
        self._config = config
        self.meta: dict = {}
        self.embed = nn.Sequential(nn.Linear(3, width), nn.ReLU(inplace=True), nn.Linear(width, width))
        self.blocks = nn.ModuleList(_Block(width, heads) for _ in range(layers))
        self.head = nn.Sequential(
            nn.LayerNorm(width), nn.Linear(width, width), nn.ReLU(inplace=True), nn.Linear(width, num_labels)
        )
        self.bin_score = nn.Parameter(torch.tensor(1.0))
        self.orienter = orienter
        if orienter is not None:
            if orienter.orienter is not None or not set(orienter.label_names) <= set(names):
                raise ValueError(
                    "orienter: expected a labeler of these labels (or some of them) without an orienter of its own"
                )
            if template is None or torso is None:
                raise ValueError("template, torso: needed with an orienter (see unibody.mocap.orient.torso_template)")
            check_shape(template, f"{orienter.num_labels} 3", name="template")
            check_shape(torso, f"{orienter.num_labels}", name="torso")
            if torso.dtype != torch.bool or int(torso.sum()) < 4:
                raise ValueError(f"torso: expected a bool mask of at least 4 markers, got {torso.dtype}, {torso}")
            orienter.requires_grad_(False)
            self.register_buffer("template", template.detach().to(self.bin_score.dtype).clone())
            self.register_buffer("torso", torso.clone())
            # each label's orienter label (the orienter's null for the labels it does not name)
            index = {x: i for i, x in enumerate(orienter.label_names)}
            to_orienter = [index.get(x, orienter.num_labels) for x in names] + [orienter.num_labels]
            self.register_buffer("to_orienter", torch.tensor(to_orienter), persistent=False)

    @property
    def config(self) -> LabelerConfig:
        """The settings (frozen); assigning a changed copy checks it against the weights and the orienter."""
        return self._config

    @config.setter
    def config(self, config: LabelerConfig) -> None:
        if not isinstance(config, LabelerConfig):
            raise TypeError(f"config: expected a LabelerConfig, got {type(config).__name__}")
        fixed = [f for f in _ARCHITECTURE if getattr(config, f) != getattr(self._config, f)]
        if fixed:
            raise ValueError(f"config: {', '.join(fixed)} are fixed by the weights; build a new Labeler to change them")
        check_retry(config.retry, self.orienter is not None)
        self._config = config

    def with_config(self, **changes) -> Labeler:
        """A copy of this labeler (weights, orienter, meta) with some settings changed (checked like :attr:`config`)."""
        config = replace(self._config, **changes)
        out = copy.deepcopy(self)
        out.config = config
        return out

    @property
    def num_labels(self) -> int:
        return self._config.num_labels

    def centres(self, points: torch.Tensor, mask: torch.Tensor, rule: str | None = None) -> torch.Tensor:
        """(B, 3) the point each frame is centred on (zeros for a frame without real points).

        ``rule`` ("median" or "midrange") overrides the model's ``centre``.
        """
        real = torch.where(mask[..., None], points, torch.nan)
        if (rule or self._config.centre) == "median":
            centre = torch.nanmedian(real, dim=1).values
        else:  # middle of the 5-95 % range: a crowd of extra markers on the feet does not move it
            q = torch.nanquantile(real, torch.tensor([0.05, 0.95], dtype=real.dtype, device=real.device), dim=1)
            centre = 0.5 * (q[0] + q[1])
        return torch.nan_to_num(centre)

    def scores(self, points: torch.Tensor, mask: torch.Tensor, centre: torch.Tensor | None = None) -> torch.Tensor:
        """Point-to-label scores (B, N, L) before Sinkhorn; same arguments as :meth:`forward`.

        ``centre`` (B, 3) overrides the frames' centres (default :meth:`centres`).
        """
        centre = self.centres(points, mask) if centre is None else centre
        with torch.autocast(points.device.type, dtype=self.autocast or torch.bfloat16, enabled=bool(self.autocast)):
            x = self.embed(torch.where(mask[..., None], points - centre[:, None], 0.0))
            # A frame without real points attends to its (ignored) padding rather than to nothing (NaN).
            key_ok = mask | ~mask.any(dim=1, keepdim=True)
            key_bias = torch.where(key_ok, 0.0, _NEG_BIAS).to(x.dtype)[:, None, None, :]
            for block in self.blocks:
                x = block(x, key_bias)
            return self.head(x).to(points.dtype)

    def set_autocast(self, dtype: torch.dtype | None) -> Labeler:
        """Run the network (and the orienter's) in mixed precision, or not (``None``, the default).

        With ``torch.bfloat16`` the products run in bfloat16 under :func:`torch.autocast`; centring,
        Sinkhorn, decoding and orientation stay in the points' dtype. On CPUs with AMX (Intel Xeon
        4th generation and later) batches of hundreds of frames label 9-17 % faster (batch 1
        slower); the labels move a little (benchmarks/README.md). Not saved with the weights.
        Returns the labeler.
        """
        if dtype not in (None, torch.bfloat16, torch.float16):
            raise ValueError(f"dtype: expected None, torch.bfloat16 or torch.float16, got {dtype!r}")
        for m in (self, self.orienter):
            if m is not None:
                m.autocast = dtype
        return self

    def forward(
        self, points: torch.Tensor, mask: torch.Tensor, *, refine: int | None = None, retry: float | None = None
    ) -> torch.Tensor:
        """Log assignment plan of each frame.

        Args:
            points: (B, N, 3) m, unibody frame (Y up); padding slots are ignored (may hold anything).
            mask: (B, N) bool, True for real points (markers and ghosts).
            refine: re-centring passes (default: the model's ``refine``; training uses 0).
            retry: confidence below which a frame is oriented again (default: the model's
                ``retry``; training uses 0).

        Returns:
            (B, N+1, L+1) log plan (see :func:`~unibody.mocap.sinkhorn.log_sinkhorn`): row i,
            column j < L is log P(point i has label j); column L is the null label; row N is
            the "label unmatched" dustbin.

        Raises:
            ValueError: bad shapes or non-finite real points.
            TypeError: a non-bool mask or points whose dtype/device differ from the model.
        """
        check_shape(points, "B N 3", name="points")
        check_shape(mask, "B N", name="mask", sizes={"B": points.shape[0], "N": points.shape[1]})
        if mask.dtype != torch.bool:
            raise TypeError(f"mask: expected a bool tensor, got {mask.dtype}")
        check_like(points, self.bin_score, "points", owner="the labeler")
        check_finite(torch.where(mask[..., None], points, 0.0), "points")
        refine = self._config.refine if refine is None else refine
        retry = self._config.retry if retry is None else retry
        if refine < 0:
            raise ValueError(f"refine: expected >= 0, got {refine}")
        check_retry(retry, self.orienter is not None)
        if self.orienter is None:
            return self._label(points, mask, self.centres(points, mask, "midrange" if refine else None), refine)
        rot, centre = self.orient(points, mask)
        plan = self._label(points @ rot.transpose(1, 2), mask, centre, refine)
        return self._retry(points, mask, plan, retry, refine) if retry else plan

    def _label(self, points: torch.Tensor, mask: torch.Tensor, centre: torch.Tensor, refine: int) -> torch.Tensor:
        """Log plan of frames already centred on ``centre`` (and oriented), after ``refine`` re-centrings."""
        if len(points) > _CHUNK and points.device.type == "cpu":  # frames are independent: the same plans
            parts = (points.split(_CHUNK), mask.split(_CHUNK), centre.split(_CHUNK))
            return torch.cat([self._label(p, m, c, refine) for p, m, c in zip(*parts, strict=True)])
        iters, null = self._config.sinkhorn_iters, self.num_labels
        for _ in range(refine):
            with torch.no_grad():
                plan = log_sinkhorn(self.scores(points, mask, centre), self.bin_score, mask, iters)
                marker = mask & (plan[:, :-1].argmax(dim=2) != null)
                marker = torch.where(marker.sum(dim=1, keepdim=True) >= 3, marker, mask)
                centre = self.centres(points, marker)
        return log_sinkhorn(self.scores(points, mask, centre), self.bin_score, mask, iters)

    @torch.no_grad()
    def orient(self, points: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Rotation of each frame into the rest frame (B, 3, 3), and the rotated frame's centre (B, 3).

        The orienter labels each frame; the points it gives torso labels, weighted by its
        confidence, are fitted to the template (:func:`~unibody.mocap.orient.fit_rotation`);
        the centre is the ``centre`` rule over the rotated points it called markers (all
        points if fewer than 3). Same arguments as :meth:`forward`.
        """
        if self.orienter is None:
            raise ValueError("orient: this labeler has no orienter")
        points = torch.where(mask[..., None], points, 0.0)  # padding may hold anything
        labels, confidence = predict(self.orienter(points, mask), mask)
        rot = self._torso_rotation(points, mask, labels, confidence)
        return rot, self._marker_centres(points @ rot.transpose(1, 2), mask, labels != self.orienter.num_labels)

    def _torso_rotation(self, points, mask, labels, confidence) -> torch.Tensor:
        """(B, 3, 3) fit of the points given torso labels (orienter labels, (B, N)) to the template."""
        null = self.orienter.num_labels
        known = labels.clamp_max(null - 1)
        weights = torch.where(mask & (labels != null) & self.torso[known], confidence, 0.0)
        return fit_rotation(points, weights, self.template[known])

    def _marker_centres(self, points, mask, marker) -> torch.Tensor:
        """:meth:`centres` of the real points ``marker`` calls markers (all of them if fewer than 3)."""
        marker = mask & marker
        return self.centres(points, torch.where(marker.sum(dim=1, keepdim=True) >= 3, marker, mask))

    def _retry(self, points, mask, plan, retry: float, refine: int) -> torch.Tensor:
        """Orient again the frames whose mean confidence in ``plan`` is below ``retry``; keep the surest plan.

        Candidates: the orienter's labels (one pass) of the frame turned by each of
        :data:`~unibody.mocap.orient.TILTS` (a fit within 2 degrees of an earlier one of the
        frame is not labelled again: the 13 tilts of an unsure frame fit to about 5 distinct
        orientations); then the fit of this labeler's own labels of the best so far, turned by
        each of :data:`~unibody.mocap.orient.NUDGES`.
        """
        low = (_surety(plan, mask) < retry).nonzero()[:, 0]
        if not len(low):
            return plan
        p, m = torch.where(mask[low, :, None], points[low], 0.0), mask[low]
        with torch.no_grad():  # all candidates of all frames in one pass of each stage
            best = plan[low].detach()
            sure = _surety(best, m)
            k, n, null = len(TILTS), len(low), self.orienter.num_labels
            tilts = TILTS.to(p)
            q, mq = (p[None] @ tilts[:, None].transpose(-1, -2)).flatten(0, 1), m.repeat(k, 1)  # (K * F, N, .)
            labels, conf = predict(self.orienter(q, mq, refine=0), mq)
            rots = self._torso_rotation(q, mq, labels, conf).unflatten(0, (k, n))
            rots = rots @ tilts[:, None]  # back from each tilt
            marker = labels.unflatten(0, (k, n)) != null
            best, sure = self._surest(p, m, rots, marker, best, sure, refine, _distinct(rots))
            labels, conf = predict(best, m)
            rots = NUDGES.to(p)[:, None] @ self._torso_rotation(p, m, self.to_orienter[labels], conf)
            marker = (labels != self.num_labels).expand(len(NUDGES), -1, -1)
            best, _ = self._surest(p, m, rots, marker, best, sure, refine)
        plan = plan.clone()
        plan[low] = best
        return plan

    def _surest(self, p, m, rots, marker, best, sure, refine: int, keep=None) -> tuple[torch.Tensor, torch.Tensor]:
        """Label frames p (F, N, 3) in K orientations rots (K, F, 3, 3), each centred on the points
        ``marker`` (K, F, N) calls markers, where ``keep`` (K, F; default all) says so; keep a
        candidate where it is surer than ``best``."""
        k, n = rots.shape[:2]
        keep = torch.ones(k, n, dtype=torch.bool, device=p.device) if keep is None else keep
        cand, frame = keep.nonzero().unbind(1)  # row-major: candidates of a frame in order
        mk = m[frame]
        pts = p[frame] @ rots[cand, frame].transpose(1, 2)
        cands = self._label(pts, mk, self._marker_centres(pts, mk, marker[cand, frame]), refine)
        surety = torch.full((k, n), -1.0, dtype=sure.dtype, device=p.device)
        surety[cand, frame] = _surety(cands, mk)
        top, at = surety.max(dim=0)
        better = top > sure  # ties keep the plan before
        row = keep.flatten().cumsum(0).view(k, n) - 1  # each kept candidate's row in cands
        chosen = cands[row[at, torch.arange(n, device=p.device)]]
        return torch.where(better[:, None, None], chosen, best), torch.where(better, top, sure)

    def save(self, path: str | Path, meta: dict | None = None) -> None:
        """Write weights, configuration, label names and ``meta`` (default :attr:`meta`) to one file.

        ``meta`` may hold only str/int/float/bool/None and lists/dicts of them, so that
        :meth:`load` can read the file with ``torch.load(weights_only=True)``.
        """
        meta = dict(self.meta if meta is None else meta)
        _check_plain(meta, "meta")
        state = {k: v.detach().cpu() for k, v in self.state_dict().items()}
        config = self._config.to_dict()
        if self.orienter is not None:
            config["orienter"] = self.orienter.config.to_dict()
            if self.orienter.label_names != self.label_names:
                config["orienter"]["label_names"] = list(self.orienter.label_names)
        payload = {"format": LABELER_FORMAT, "config": config, "label_names": list(self.label_names),
                   "meta": meta, "state_dict": state}  # fmt: skip
        with atomic_path(path) as tmp:
            torch.save(payload, tmp)

    @classmethod
    def from_config(cls, config: LabelerConfig, **kwargs) -> Labeler:
        """A new (untrained) labeler with ``config``'s settings; ``kwargs``: the other :class:`Labeler` arguments."""
        if not isinstance(config, LabelerConfig):
            raise TypeError(f"config: expected a LabelerConfig, got {type(config).__name__}")
        return cls(config.num_labels, **{k: v for k, v in config.to_dict().items() if k != "num_labels"}, **kwargs)

    @classmethod
    def load(cls, path: str | Path, *, map_location: str | torch.device = "cpu") -> Labeler:
        """Read a labeler written by :meth:`save` (safe load: ``weights_only=True``).

        Raises:
            ValueError: ``path`` is no such file (other bytes, another model, missing or
                malformed entries, NaN/inf weights); the message names it.
        """
        what = "a labeler written by Labeler.save"
        payload = read_weights(path, what, map_location=map_location)
        if payload.get("format") != LABELER_FORMAT:
            raise ValueError(f"{path}: not {what} (format {payload.get('format')!r}, expected {LABELER_FORMAT!r})")
        with rebuilding(path, what):
            cfg = dict(payload["config"])
            names = payload["label_names"]
            parts = {}
            if "orienter" in cfg:  # placeholders, filled by the state dict
                ocfg = dict(cfg.pop("orienter"))
                onames = ocfg.pop("label_names", names)
                n = ocfg["num_labels"]
                parts = {"orienter": cls.from_config(LabelerConfig.from_dict(ocfg), label_names=onames),
                         "template": torch.zeros(n, 3), "torso": torch.arange(n) < 4}  # fmt: skip
            model = cls.from_config(LabelerConfig.from_dict(cfg), label_names=names, **parts)
            model.load_state_dict(payload["state_dict"])
            model.meta = payload["meta"]
        return model


def labeling_loss(log_plan: torch.Tensor, batch: MocapBatch) -> torch.Tensor:
    """Weighted NLL of the ground-truth augmented assignment (paper 003 eq. 6).

    The target G' has a 1 at (i, label_i) for every real point i (column L for ghosts)
    and a 1 at (N, l) in the dustbin row for every label l that no real point carries
    (derived from ``batch.labels``, so the target always satisfies the plan's marginals).
    Null rows and the dustbin-row entries of a frame are weighted by 1 / (number of null
    points of the frame, at least 1), every other entry by 1; the loss is
    -sum(W G' log A') / sum(G'). Padding slots and the dustbin corner are not part of it.

    Args:
        log_plan: (B, N+1, L+1) output of :class:`Labeler`.
        batch: ground truth; uses ``labels`` (B, N) in [0, L] and ``mask`` (B, N).

    Returns:
        Scalar loss.
    """
    labels, mask = batch.labels, batch.mask
    b, n1, l1 = log_plan.shape
    n, num_labels = n1 - 1, l1 - 1
    check_shape(labels, f"{b} {n}", name="batch.labels")
    check_shape(mask, f"{b} {n}", name="batch.mask")
    if bool(((labels < 0) | (labels > num_labels))[mask].any()):
        raise ValueError(f"batch.labels: real points need labels in [0, {num_labels}]")
    target = torch.where(mask, labels, num_labels)
    is_null = mask & (target == num_labels)
    w_null = 1.0 / is_null.sum(dim=1).clamp(min=1).to(log_plan.dtype)  # (B,)
    row_logp = log_plan[:, :n].gather(2, target[..., None])[..., 0]  # (B, N)
    row_w = torch.where(is_null, w_null[:, None], 1.0) * mask
    seen = torch.zeros(b, num_labels + 1, dtype=torch.bool, device=labels.device)
    seen.scatter_(1, target, mask)  # padding scatters False, never marks a label as seen
    unmatched = ~seen[:, :num_labels]  # (B, L)
    bin_logp = log_plan[:, n, :num_labels]
    total = (row_w * row_logp).sum() + (w_null[:, None] * torch.where(unmatched, bin_logp, 0.0)).sum()
    count = mask.sum() + unmatched.sum()
    return -total / count.clamp(min=1)


def check_retry(retry: float, two_stage: bool) -> None:
    """Raise ValueError unless ``retry`` is 0, or a confidence in (0, 1] for a labeler with an orienter."""
    if not 0.0 <= retry <= 1.0 or (retry and not two_stage):
        raise ValueError(f"retry: expected 0, or a confidence in (0, 1] with an orienter, got {retry}")


def _distinct(rots: torch.Tensor, degrees: float = 2.0) -> torch.Tensor:
    """(K, F) bool: rotation k of frame f (rots (K, F, 3, 3)) is more than ``degrees`` from each
    earlier one of that frame (most tilts of an unsure frame fit to one of a few orientations)."""
    near = rotation_angle(rots[:, None].transpose(-1, -2) @ rots[None]) < math.radians(degrees)  # (K, K, F)
    earlier = torch.ones(len(rots), len(rots), dtype=torch.bool, device=rots.device).tril(-1)
    return ~(near & earlier[..., None]).any(dim=1)


def _surety(log_plan: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """(B,) mean confidence of each frame's decoded labels over its real points."""
    return predict(log_plan, mask)[1].sum(dim=1) / mask.sum(dim=1).clamp_min(1)


def predict(log_plan: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Decode labels from a log plan, one point per label per frame.

    Each real point takes its most probable column (a label or null). When several points
    of a frame take the same label, the most confident keeps it and the others become
    null (ties go to the lower point index). A second-choice label is never tried: rows
    of the plan sum to 1, so no other label of a point can have probability above 0.5.

    Args:
        log_plan: (B, N+1, L+1) output of :class:`Labeler`.
        mask: (B, N) bool, real points.

    Returns:
        labels: (B, N) int64 in [0, L], L = null (also for padding); no label twice in a frame.
        confidence: (B, N) probability of the returned label (0 for padding).
    """
    b, n1, l1 = log_plan.shape
    check_shape(mask, f"{b} {n1 - 1}", name="mask")
    null = l1 - 1
    prob = log_plan[:, :-1].detach().exp()
    conf, labels = prob.max(dim=2)
    labels = torch.where(mask, labels, null)
    # point j beats point i when it has the same (non-null) label and more confidence
    same = (labels[:, :, None] == labels[:, None, :]) & (labels[:, :, None] != null)
    idx = torch.arange(n1 - 1, device=labels.device)
    earlier = idx[None, :] < idx[:, None]  # [i, j]: j comes before i
    beats = same & ((conf[:, None, :] > conf[:, :, None]) | ((conf[:, None, :] == conf[:, :, None]) & earlier))
    lost = beats.any(dim=2)
    labels = torch.where(lost, null, labels)
    conf = torch.where(lost, prob[..., null], conf)
    return labels, torch.where(mask, conf, 0.0)


@dataclass(frozen=True, slots=True)
class FrameLabels:
    """Per-frame labels of a sequence and the probabilities they were decoded from.

    Attributes:
        labels: (T, N) int64 in [0, L] (:func:`predict`: no label twice in a frame; L = null,
            also for missing points).
        prob: (T, N, L+1) float32, each point's row of the plan (probabilities of the L labels
            and null; they sum to 1); zeros for missing points.
        surety: (T,) float32, each frame's mean confidence in its labels (what a retry is
            decided on; 0 for a frame without points).
    """

    labels: torch.Tensor
    prob: torch.Tensor
    surety: torch.Tensor


@torch.no_grad()
def label_frames(model: Labeler, points: torch.Tensor, batch: int = 256) -> torch.Tensor:
    """Label every frame of a sequence.

    Args:
        model: a trained :class:`Labeler`.
        points: (T, N, 3) m, unibody frame (Y up); NaN rows are missing points.
        batch: frames per forward pass.

    Returns:
        (T, N) int64 labels in [0, L]; L (null) for missing points and for points the
        model calls ghosts.
    """
    return _label_frames(model, points, batch, False).labels


@torch.no_grad()
def frame_probabilities(
    model: Labeler, points: torch.Tensor, batch: int = 256, *, retry: float | None = None
) -> FrameLabels:
    """:func:`label_frames` and each point's label probabilities (the evidence tracklets weigh).

    ``retry`` overrides the model's retry confidence (see :class:`Labeler`; 0: no retries).
    """
    return _label_frames(model, points, batch, True, retry)


@torch.no_grad()
def sequence_probabilities(
    model: Labeler, points: torch.Tensor, batch: int = 256, *, config: TrackletConfig | None = None
) -> FrameLabels:
    """:func:`frame_probabilities` of a sequence whose columns will be settled (:func:`~.tracklets.settle_tracklets`).

    A retry (the model's ``retry`` confidence) orients an unsure frame again, at about ten times
    a frame's cost, and on a whole sequence most unsure frames cannot change any column's
    settled label. So every frame is labelled once without retries; the columns' spans and
    their evidence are formed (:func:`~.tracklets.undecided_frames`); only the unsure frames
    with a point in a span whose lead is small enough for them to overturn are labelled again,
    with retries. Same arguments as :func:`frame_probabilities`; ``config`` is the tracklets'.
    """
    from .tracklets import undecided_frames

    retry = model.config.retry if model.orienter is not None else 0.0
    first = _label_frames(model, points, batch, True, 0.0)
    visible = torch.isfinite(points).all(dim=2)
    unsure = (first.surety < retry) & visible.any(dim=1)
    if not retry or not bool(unsure.any()):
        return first
    redo = undecided_frames(first.prob, visible.cpu(), unsure.cpu(), config).nonzero()[:, 0].to(points.device)
    if not len(redo):
        return first
    again = _label_frames(model, points[redo], batch, True, retry)
    labels, prob, surety = first.labels.clone(), first.prob.clone(), first.surety.clone()
    labels[redo], prob[redo], surety[redo] = again.labels, again.prob, again.surety
    return FrameLabels(labels, prob, surety)


def _label_frames(
    model: Labeler, points: torch.Tensor, batch: int, keep_prob: bool, retry: float | None = None
) -> FrameLabels:
    check_shape(points, "T N 3", name="points")
    check_like(points, model.bin_score, "points", owner="the labeler")
    if batch < 1:
        raise ValueError(f"batch: expected >= 1, got {batch}")
    visible = torch.isfinite(points).all(dim=2)
    out = torch.full(visible.shape, model.num_labels, dtype=torch.long, device=points.device)
    shape = (*visible.shape, model.num_labels + 1) if keep_prob else (0, 0, 0)
    prob = torch.zeros(shape, dtype=torch.float32, device=points.device)
    surety = torch.zeros(visible.shape[0], dtype=torch.float32, device=points.device)
    was_training = model.training
    model.eval()
    try:
        for start in range(0, points.shape[0], batch):
            vis = visible[start : start + batch]
            # visible points first (stable), then cut the frame to the largest visible count
            order = torch.argsort((~vis).to(torch.int8), dim=1, stable=True)
            k = max(int(vis.sum(dim=1).max()), 1)
            order = order[:, :k]
            mask = vis.gather(1, order)
            pts = points[start : start + batch].gather(1, order[..., None].expand(-1, -1, 3))
            pts = torch.where(mask[..., None], pts, 0.0)
            plan = model(pts, mask, retry=retry)
            labels, conf = predict(plan, mask)
            surety[start : start + batch] = conf.sum(dim=1) / mask.sum(dim=1).clamp_min(1)
            out[start : start + batch].scatter_(1, order, labels)
            if keep_prob:
                rows = torch.where(mask[..., None], plan[:, :-1].exp(), 0.0).float()
                prob[start : start + batch].scatter_(1, order[..., None].expand(-1, -1, rows.shape[2]), rows)
    finally:
        model.train(was_training)
    return FrameLabels(out, prob, surety)
