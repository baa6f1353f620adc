"""The soft-alignment registration network (Makovetskii et al., 2024; see the README's citation).

    P, Q (B, N, 3), (B, M, 3)
      -> radius-capped K-neighbourhoods of every point (computed once per cloud)
      -> encoder: five layers "gather K neighbours -> 1x1 conv -> BatchNorm -> ReLU -> max over K",
         channels 3 -> 64 -> 128 -> 256 -> 256 -> 512; a 512-d descriptor per point
         (with ``NetConfig.relative``, the first layer sees neighbour offsets, see RelativeEdgeLayer)
      -> (with ``NetConfig.overlap``) logits o_i, o_j that a point lies in the overlap, from
         attention within and between the two clouds' descriptors (:class:`OverlapHead`)
      -> W = row-softmax(<f_i, g_j> / tau [+ log sigmoid(o_j)])       (B, N, M)
      -> virtual points vq_i = sum_j W_ij q_j, weights w_i = max_j W_ij [x sigmoid(o_i)]
      -> weighted Procrustes -> R (B, 3, 3), t (B, 3) with Q ~ R P + t

The layers are computed in an exact, K-times cheaper form. A 1x1 conv acts on each point alone,
so conv(gather(f)) = gather(conv(f)): the linear map runs on the N points, then the gather. In
training, BatchNorm over the gathered (B, C, K, N) tensor equals BatchNorm over the N points with
each point weighted by the number of neighbourhoods it appears in. BN and ReLU are elementwise
and commute with the gather too. What remains is the gather-max, done row-wise without
materialising the (B, N, K, C) tensor for backward (only the arg-max is kept).
:class:`LiteralEdgeLayer` is the paper's conv2d form, kept as the reference the tests and the
benchmarks compare against.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import List, Optional, Tuple

import torch
from torch import nn
from torch.nn import functional as F

from .errors import refuse_out_of_range
from .procrustes import weighted_procrustes


@dataclass(frozen=True)
class NetConfig:
    """Architecture settings; saved inside every exported model and its card.

    Attributes:
        k: neighbourhood size K (the point itself included).
        radius: neighbourhood radius r, in the normalised frame where objects have radius ~1.
        channels: output channels of the five encoder layers.
        shared_encoder: one encoder for both clouds (True) or one per cloud, as the paper's
            parameter count suggests (False).
        learn_temperature: learn tau of the softmax (initialised at sqrt(descriptor size)).
        relative: the first layer sees each neighbour's offset x_j - x_i instead of its
            coordinates x_j, which makes the descriptors independent of where the cloud's
            centroid lies (a cropped cloud's centroid moves with the crop).
        overlap: width of the overlap head (0: none), :class:`OverlapHead`: it predicts which
            points of each cloud lie in the overlap, and the alignment leaves out the rest (a
            descriptor computed from one cloud alone cannot tell).
        overlap_layers: the head's attention blocks.
    """

    k: int = 32
    radius: float = 0.25
    channels: Tuple[int, ...] = (64, 128, 256, 256, 512)
    shared_encoder: bool = True
    learn_temperature: bool = True
    relative: bool = False
    overlap: int = 0
    overlap_layers: int = 2

    def to_dict(self) -> dict:
        d = asdict(self)
        d["channels"] = list(self.channels)
        return d

    def validate(self) -> None:
        """InputError naming the first setting out of its range."""
        checks = [
            ("k", self.k >= 1, "at least 1"),
            ("radius", self.radius > 0, "positive"),
            ("channels", len(self.channels) >= 1 and all(c >= 1 for c in self.channels), "a list of one or more positive widths"),
            ("overlap", self.overlap >= 0, "at least 0 (0: no overlap head)"),
            ("overlap_layers", self.overlap_layers >= 0, "at least 0"),
        ]
        refuse_out_of_range(self, checks, "net")

    @classmethod
    def from_dict(cls, d: dict) -> "NetConfig":
        d = dict(d)
        if "channels" in d:
            d["channels"] = tuple(d["channels"])
        return cls(**d)


def ball_query(points: torch.Tensor, k: int, radius: float) -> torch.Tensor:
    """Indices of each point's neighbours within `radius`, at most `k`, nearest first.

    The point itself comes first. Neighbourhoods with fewer than k points within the radius are
    filled with copies of the point itself; with more, the farthest are dropped.

    Args:
        points: (B, N, 3).
        k: neighbourhood size; must be <= N.
        radius: neighbourhood radius, same units as points.
    Returns:
        (B, N, k) int64 indices into the N points.
    """
    n = points.shape[1]
    if k > n:
        raise ValueError(f"neighbourhood size k={k} exceeds the number of points {n}")
    d2 = torch.cdist(points, points).square()  # (B, N, N)
    # Self-distance is exactly 0 only up to cdist's rounding; force it so the point comes first.
    d2 = d2 - torch.eye(n, dtype=d2.dtype, device=d2.device)
    dist, idx = torch.topk(d2, k, dim=-1, largest=False, sorted=True)
    outside = dist > radius * radius
    return torch.where(outside, idx[:, :, :1].expand_as(idx), idx)


def neighbour_multiplicity(idx: torch.Tensor, n: int, dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """How many neighbourhoods each point appears in (with repeats).

    Args:
        idx: (B, N, K) neighbour indices.
        n: number of points N.
        dtype: floating dtype of the result.
    Returns:
        (B, N) counts; each row sums to N * K.
    """
    b = idx.shape[0]
    flat = idx.reshape(b, -1)
    counts = torch.zeros(b, n, dtype=dtype, device=idx.device)
    return counts.scatter_add_(1, flat, torch.ones(flat.shape, dtype=dtype, device=idx.device))


def _flatten_neighbours(idx: torch.Tensor, n: int) -> torch.Tensor:
    """(B, N, K) per-cloud indices -> (B*N, K) indices into the (B*N, C) stacked rows."""
    b = idx.shape[0]
    offset = (torch.arange(b, device=idx.device) * n).view(b, 1, 1)
    return (idx + offset).reshape(b * n, idx.shape[2])


def _gather_argmax_rows(rows: torch.Tensor, flat: torch.Tensor, chunk: int = 512) -> Tuple[torch.Tensor, torch.Tensor]:
    """max_k rows[flat[:, k]] for (M, C) rows and (M, K) indices, and the slot k of the first
    maximum, as float: the forward pass of training on the CPU, `chunk` rows at a time so that a
    step's working set stays in cache (docs/speed.md).

    Comparisons producing bool tensors and masked writes are several times slower than float
    arithmetic on CPU, so "cand > best" is computed as sign(relu(cand - best)) in float, and the
    slot as a running max of k * that step (k grows, so a later strict improvement wins).
    """
    if rows.device.type != "cpu":
        return _gather_argmax_rows_at_once(rows, flat)
    m, k_total = flat.shape
    out = torch.empty(m, rows.shape[1], dtype=rows.dtype, device=rows.device)
    arg = torch.zeros_like(out)
    # Scratch buffers reused across steps: fresh allocations each step cost page faults.
    cand = torch.empty(min(m, chunk), rows.shape[1], dtype=rows.dtype, device=rows.device)
    step = torch.empty_like(cand)
    for s in range(0, m, chunk):
        f = flat[s : s + chunk]
        best = out[s : s + chunk]
        slot = arg[s : s + chunk]
        c = cand[: f.shape[0]]
        st = step[: f.shape[0]]
        torch.index_select(rows, 0, f[:, 0], out=best)
        for k in range(1, k_total):
            torch.index_select(rows, 0, f[:, k], out=c)
            torch.sub(c, best, out=st).relu_().sign_().mul_(float(k))
            torch.maximum(slot, st, out=slot)
            torch.maximum(best, c, out=best)
    return out, arg


def _gather_argmax_rows_at_once(rows: torch.Tensor, flat: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
    """As :func:`_gather_argmax_rows`, in one gather of all K neighbours: (M, K, C) at once.

    On a GPU the chunked loops above launch thousands of tiny kernels per layer and leave it
    idle; here, memory is plentiful and one gather plus one reduction is fastest. Among equal
    maxima any slot may be returned (each is a valid subgradient).
    """
    out, slot = rows[flat].max(dim=1)
    return out, slot.to(rows.dtype)


class _GatherMax(torch.autograd.Function):
    """out[m, c] = max_k rows[flat[m, k], c], keeping only the arg-max for backward."""

    @staticmethod
    def forward(ctx, rows: torch.Tensor, flat: torch.Tensor) -> torch.Tensor:  # type: ignore[override]
        out, slot = _gather_argmax_rows(rows, flat)
        ctx.save_for_backward(torch.gather(flat, 1, slot.long()))
        ctx.m = rows.shape[0]
        return out

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):  # type: ignore[override]
        (source_row,) = ctx.saved_tensors
        grad_rows = torch.zeros(ctx.m, grad_out.shape[1], dtype=grad_out.dtype, device=grad_out.device)
        grad_rows.scatter_add_(0, source_row, grad_out)
        return grad_rows, None


@torch.jit.unused
def _gather_max_autograd(rows: torch.Tensor, flat: torch.Tensor) -> torch.Tensor:
    return _GatherMax.apply(rows, flat)


def _gather_max_columns(rows: torch.Tensor, cols: List[torch.Tensor]) -> torch.Tensor:
    """max_k rows[cols[k]] for (M, C) rows and K contiguous (M,) index columns, into reused
    buffers (no gradient): (M, C)."""
    out = rows.index_select(0, cols[0])
    cand = torch.empty_like(out)
    for k in range(1, len(cols)):
        torch.index_select(rows, 0, cols[k], out=cand)
        torch.maximum(out, cand, out=out)
    return out


def neighbour_columns(idx: torch.Tensor) -> List[torch.Tensor]:
    """(B, N, K) neighbour indices -> K contiguous (B*N,) columns indexing the stacked (B*N, C)
    rows: column k holds every point's k-th neighbour. Made once per cloud, for all layers."""
    return _flatten_neighbours(idx, idx.shape[1]).t().contiguous().unbind(0)


def _linear_gather_max(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, cols: List[torch.Tensor], block: int = 256) -> torch.Tensor:
    """max_k ReLU(weight x_j + bias) over each neighbourhood, at inference on the CPU.

    The linear map runs one block of output channels at a time, so each block comes out
    contiguous and its K gathers stay nearer the cache; ReLU commutes with the max (block sizes:
    docs/speed.md).

    Args:
        x: (B, N, C_in); weight: (C_out, C_in); bias: (C_out,); cols: :func:`neighbour_columns`.
    Returns:
        (B, N, C_out).
    """
    b, n, _ = x.shape
    rows = x.reshape(b * n, x.shape[2])
    blocks: List[torch.Tensor] = []
    for s in range(0, weight.shape[0], block):
        z = torch.addmm(bias[s : s + block], rows, weight[s : s + block].t())
        blocks.append(_gather_max_columns(z, cols))
    return torch.relu_(torch.cat(blocks, dim=1)).view(b, n, weight.shape[0])


def gather_max(z: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """Max of point features over each neighbourhood.

    One implementation per case: without gradients, a loop over the K neighbour columns
    (:func:`_gather_max_columns`; on the CPU in channel blocks when scripted) or, off the CPU in
    eager mode, one gather; with gradients, :class:`_GatherMax`, which keeps only the arg-max for
    backward (rows in chunks on the CPU, one gather elsewhere).

    Args:
        z: (B, N, C) point features.
        idx: (B, N, K) neighbour indices.
    Returns:
        (B, N, C) with out[b, i] = max_k z[b, idx[b, i, k]].
    """
    b, n, c = z.shape
    rows = z.reshape(b * n, c)
    if torch.jit.is_scripting():
        # A single loop over K: 4x faster than one big gather at inference, and unlike the
        # chunked double loop it does not send TorchScript's optimiser into multi-second passes.
        # Contiguous index columns and reused buffers: faster than slicing flat[:, k] and
        # allocating each step.
        # (out= variants do not record gradients: only without them.)
        cols = neighbour_columns(idx)
        if rows.requires_grad:
            out = rows.index_select(0, cols[0])
            for k in range(1, len(cols)):
                out = torch.maximum(out, rows.index_select(0, cols[k]))
            return out.view(b, n, c)
        # On the CPU, channel blocks: the rows gathered K times stay in cache (docs/speed.md).
        block = 64
        if rows.device.type != "cpu" or c <= block:
            return _gather_max_columns(rows, cols).view(b, n, c)
        blocks: List[torch.Tensor] = []
        for s in range(0, c, block):
            blocks.append(_gather_max_columns(rows[:, s : s + block].contiguous(), cols))
        return torch.cat(blocks, dim=1).view(b, n, c)
    if not z.requires_grad:
        if rows.device.type != "cpu":
            return rows[_flatten_neighbours(idx, n)].amax(dim=1).view(b, n, c)
        return _gather_max_columns(rows, neighbour_columns(idx)).view(b, n, c)
    return _gather_max_autograd(rows, _flatten_neighbours(idx, n)).view(b, n, c)


class MultiplicityBatchNorm(nn.Module):
    """BatchNorm of per-point features, each point weighted by its neighbourhood count.

    Equal, in training, to ``nn.BatchNorm2d`` over the gathered (B, C, K, N) tensor; in eval it
    applies the running statistics like any BatchNorm. Same parameters, buffers and momentum
    semantics as ``nn.BatchNorm2d``.
    """

    def __init__(self, channels: int, eps: float = 1e-5, momentum: float = 0.1) -> None:
        super().__init__()
        self.eps = eps
        self.momentum = momentum
        self.weight = nn.Parameter(torch.ones(channels))
        self.bias = nn.Parameter(torch.zeros(channels))
        self.register_buffer("running_mean", torch.zeros(channels))
        self.register_buffer("running_var", torch.ones(channels))
        self.register_buffer("num_batches_tracked", torch.tensor(0, dtype=torch.long))

    def forward(self, y: torch.Tensor, multiplicity: torch.Tensor) -> torch.Tensor:
        """y: (B, N, C) features; multiplicity: (B, N) counts summing to N*K per cloud."""
        if self.training:
            m = multiplicity.reshape(1, -1)  # (1, B*N)
            rows = y.reshape(-1, y.shape[-1])  # (B*N, C)
            total = multiplicity.sum()
            mean = torch.matmul(m, rows).squeeze(0) / total
            var = torch.matmul(m, (rows - mean).square()).squeeze(0) / total
            self.track(mean, var, total)
        else:
            mean = self.running_mean
            var = self.running_var
        return (y - mean) * torch.rsqrt(var + self.eps) * self.weight + self.bias

    def fold(self, weight: torch.Tensor, bias: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """The eval-mode BatchNorm of a linear map's output as one linear map:
        BN(W x + b) = W' x + b' for W (C, C_in), b (C,); returns (W', b')."""
        s = self.weight * torch.rsqrt(self.running_var + self.eps)
        return weight * s.unsqueeze(1), (bias - self.running_mean) * s + self.bias

    def track(self, mean: torch.Tensor, var: torch.Tensor, count: torch.Tensor) -> None:
        """Update the running statistics from a batch's (C,) mean and biased variance over
        `count` values per channel, as ``nn.BatchNorm2d`` does."""
        with torch.no_grad():
            self.num_batches_tracked.add_(1)
            unbiased = var * (count / torch.clamp(count - 1.0, min=1.0))
            self.running_mean.mul_(1.0 - self.momentum).add_(self.momentum * mean)
            self.running_var.mul_(1.0 - self.momentum).add_(self.momentum * unbiased)


class EdgeLayer(nn.Module):
    """One encoder layer, exact fast form: linear on N points -> weighted BN -> ReLU -> gather-max."""

    def __init__(self, c_in: int, c_out: int) -> None:
        super().__init__()
        self.linear = nn.Linear(c_in, c_out)
        self.bn = MultiplicityBatchNorm(c_out)

    def forward(self, x: torch.Tensor, idx: torch.Tensor, multiplicity: torch.Tensor, cols: Optional[List[torch.Tensor]] = None) -> torch.Tensor:
        """x: (B, N, C_in); idx: (B, N, K); multiplicity: (B, N); cols: :func:`neighbour_columns`
        of idx on the inference path (see :class:`Encoder`), else None. Returns (B, N, C_out)."""
        if cols is not None:
            weight, bias = self.bn.fold(self.linear.weight, self.linear.bias)
            return _linear_gather_max(x, weight, bias, cols)
        z = F.relu(self.bn(self.linear(x), multiplicity))
        return gather_max(z, idx)


class RelativeEdgeLayer(nn.Module):
    """First encoder layer on neighbour offsets, exact fast form: max_j ReLU(BN(A (x_j - x_i) + c)).

    The literal form gathers K offsets per point and runs the linear map and BatchNorm on all N*K
    of them. Three facts make it as cheap as :class:`EdgeLayer`: A (x_j - x_i) = a_j - a_i with
    a = A x computed on the N points; BatchNorm's statistics over the offsets follow from their
    3x3 second moment (mean A mu + c, variance of channel k = A_k Sigma A_k^T); and BN is an affine
    map s y + b per channel, so max_j ReLU(s (a_j - a_i) + b') = ReLU(max_j (s a_j) - s a_i + b'),
    one gather-max of s a (whatever the sign of s). The bias c cancels in training, as in the
    literal form.
    """

    def __init__(self, c_in: int, c_out: int) -> None:
        super().__init__()
        self.linear = nn.Linear(c_in, c_out)
        self.bn = MultiplicityBatchNorm(c_out)

    def forward(self, x: torch.Tensor, idx: torch.Tensor, multiplicity: torch.Tensor, cols: Optional[List[torch.Tensor]] = None) -> torch.Tensor:
        """x: (B, N, C_in); idx: (B, N, K); multiplicity: unused (every offset counts once); cols:
        as for :class:`EdgeLayer`. Returns (B, N, C_out)."""
        a = torch.matmul(x, self.linear.weight.t())  # (B, N, C_out), without the bias
        bn = self.bn
        if self.training:
            b, n, c = x.shape
            rows = x.reshape(b * n, c)
            offsets = (rows[_flatten_neighbours(idx, n)] - rows.unsqueeze(1)).reshape(-1, c)  # (B*N*K, C_in)
            mu = offsets.mean(dim=0)
            centred = offsets - mu
            sigma = torch.matmul(centred.t(), centred) / offsets.shape[0]  # (C_in, C_in), biased like BatchNorm's
            mean = torch.matmul(self.linear.weight, mu) + self.linear.bias
            var = (torch.matmul(self.linear.weight, sigma) * self.linear.weight).sum(dim=1)
            bn.track(mean, var, torch.tensor(float(offsets.shape[0]), dtype=x.dtype, device=x.device))
        else:
            mean = bn.running_mean
            var = bn.running_var
        scale = bn.weight * torch.rsqrt(var + bn.eps)  # (C_out,)
        shift = bn.bias + scale * (self.linear.bias - mean)
        sa = a * scale
        if cols is not None:
            b, n, c = sa.shape
            return F.relu(_gather_max_columns(sa.reshape(b * n, c), cols).view(b, n, c) - sa + shift)
        return F.relu(gather_max(sa, idx) - sa + shift)


class LiteralEdgeLayer(nn.Module):
    """The paper's layer as written: gather to (B, C, K, N) -> Conv2d 1x1 -> BatchNorm2d -> ReLU -> max.

    K times more work than :class:`EdgeLayer`; the reference that the fast form is tested and
    benchmarked against. ``load_into`` copies its parameters into an :class:`EdgeLayer` (or, with
    ``relative``, a :class:`RelativeEdgeLayer`).
    """

    def __init__(self, c_in: int, c_out: int, relative: bool = False) -> None:
        super().__init__()
        self.relative = relative
        self.conv = nn.Conv2d(c_in, c_out, kernel_size=1, stride=1, padding=0)
        self.bn = nn.BatchNorm2d(c_out)

    def forward(self, x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        """x: (B, C_in, N); idx: (B, N, K). Returns (B, C_out, N).

        With ``relative``, each gathered neighbour x_j becomes its offset x_j - x_i."""
        b, c, n = x.shape
        k = idx.shape[2]
        flat = idx.reshape(b, 1, n * k).expand(-1, c, -1)
        grouped = torch.gather(x, 2, flat).view(b, c, n, k).transpose(2, 3)  # (B, C, K, N)
        if self.relative:
            grouped = grouped - x.unsqueeze(2)
        y = F.relu(self.bn(self.conv(grouped)))
        return y.amax(dim=2)

    def load_into(self, fast: nn.Module) -> None:
        with torch.no_grad():
            fast.linear.weight.copy_(self.conv.weight[:, :, 0, 0])
            fast.linear.bias.copy_(self.conv.bias)
            for name in ("weight", "bias", "running_mean", "running_var", "num_batches_tracked"):
                getattr(fast.bn, name).copy_(getattr(self.bn, name))


class Encoder(nn.Module):
    """Five edge layers; per-point descriptors from coordinates and neighbourhoods."""

    def __init__(self, channels: Tuple[int, ...], relative: bool = False) -> None:
        super().__init__()
        dims = [3] + list(channels)
        first = RelativeEdgeLayer(3, dims[1]) if relative else EdgeLayer(3, dims[1])
        self.layers = nn.ModuleList([first] + [EdgeLayer(dims[i], dims[i + 1]) for i in range(1, len(channels))])

    def forward(self, points: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        """points: (B, N, 3); idx: (B, N, K). Returns (B, N, channels[-1]) descriptors."""
        multiplicity = neighbour_multiplicity(idx, points.shape[1], points.dtype)
        # Inference on the CPU (scripted, no gradient): the index columns are made once for all
        # five layers, and each layer's BatchNorm is folded into its linear map.
        cols: Optional[List[torch.Tensor]] = None
        if torch.jit.is_scripting() and not self.training and not torch.is_grad_enabled() and points.device.type == "cpu":
            cols = neighbour_columns(idx)
        x = points
        for layer in self.layers:
            x = layer(x, idx, multiplicity, cols)
        return x


class LiteralEncoder(nn.Module):
    """:class:`Encoder` built from the paper's literal layers; same interface, for tests and benchmarks."""

    def __init__(self, channels: Tuple[int, ...], relative: bool = False) -> None:
        super().__init__()
        dims = [3] + list(channels)
        self.layers = nn.ModuleList([LiteralEdgeLayer(dims[i], dims[i + 1], relative and i == 0) for i in range(len(channels))])

    def forward(self, points: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        x = points.transpose(1, 2)
        for layer in self.layers:
            x = layer(x, idx)
        return x.transpose(1, 2)

    def load_into(self, fast: Encoder) -> None:
        for lit, f in zip(self.layers, fast.layers):
            lit.load_into(f)


class OverlapBlock(nn.Module):
    """Self-attention within each cloud, then attention from each cloud to the other, then a
    feed-forward layer; pre-norm, residual, one set of weights for both clouds."""

    def __init__(self, width: int, heads: int = 4) -> None:
        super().__init__()
        self.within = nn.MultiheadAttention(width, heads, batch_first=True)
        self.across = nn.MultiheadAttention(width, heads, batch_first=True)
        self.norm_within, self.norm_across, self.norm_ffn = nn.LayerNorm(width), nn.LayerNorm(width), nn.LayerNorm(width)
        self.ffn = nn.Sequential(nn.Linear(width, 2 * width), nn.ReLU(), nn.Linear(2 * width, width))

    def forward(self, a: torch.Tensor, b: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """a (B, N, W), b (B, M, W) -> the same shapes."""
        na, nb = self.norm_within(a), self.norm_within(b)
        a = a + self.within(na, na, na, need_weights=False)[0]
        b = b + self.within(nb, nb, nb, need_weights=False)[0]
        na, nb = self.norm_across(a), self.norm_across(b)
        a, b = a + self.across(na, nb, nb, need_weights=False)[0], b + self.across(nb, na, na, need_weights=False)[0]
        return a + self.ffn(self.norm_ffn(a)), b + self.ffn(self.norm_ffn(b))


class OverlapHead(nn.Module):
    """Logits that each point of the source and of the target lies in the two clouds' overlap (a
    point of the other cloud near where it truly lies; :func:`overlap_labels`), from both clouds'
    descriptors and coordinates: a projection to `width`, `layers` :class:`OverlapBlock`, a linear
    read-out. The read-out starts at zero: every logit 0, which leaves the network's poses as they
    were (a common shift of the soft assignment's scores and a common factor of the weights), so
    that a head added to a trained network starts from that network's results."""

    def __init__(self, descriptor: int, width: int, layers: int = 2) -> None:
        super().__init__()
        self.embed = nn.Linear(descriptor + 3, width)
        self.blocks = nn.ModuleList([OverlapBlock(width) for _ in range(layers)])
        self.readout = nn.Linear(width, 1)
        nn.init.zeros_(self.readout.weight)
        nn.init.zeros_(self.readout.bias)

    def forward(self, source: torch.Tensor, f: torch.Tensor, target: torch.Tensor, g: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor]:
        """source (B, N, 3), f (B, N, C), target (B or 1, M, 3), g (B or 1, M, C) -> logits (B, N), (B, M)."""
        b = source.shape[0]
        a = self.embed(torch.cat([f, source], dim=-1))
        c = self.embed(torch.cat([g, target], dim=-1)).expand(b, -1, -1)
        for block in self.blocks:
            a, c = block(a, c)
        return self.readout(a).squeeze(-1), self.readout(c).squeeze(-1)


class SoftAlignNet(nn.Module):
    """Soft-alignment registration network: returns (R, t, w) with target ~ R source + t.

    forward(source (B, N, 3), target (B, M, 3)) -> (R (B, 3, 3), t (B, 3), w (B, N)), where w_i in
    [0, 1] is the largest soft-assignment probability of source point i (times its overlap
    probability with an overlap head).
    """

    def __init__(self, config: NetConfig = NetConfig()) -> None:
        super().__init__()
        self.k = config.k
        self.radius = config.radius
        self.encoder_p = Encoder(config.channels, config.relative)
        self.encoder_q = self.encoder_p if config.shared_encoder else Encoder(config.channels, config.relative)
        log_tau = torch.tensor(0.5 * math.log(config.channels[-1]))
        if config.learn_temperature:
            self.log_tau = nn.Parameter(log_tau)
        else:
            self.register_buffer("log_tau", log_tau)
        # Empty without a head (a ModuleList, so that TorchScript compiles both cases).
        self.overlap = nn.ModuleList([OverlapHead(config.channels[-1], config.overlap, config.overlap_layers)] if config.overlap else [])

    def forward(self, source: torch.Tensor, target: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        f = self.describe_source(source, self.neighbours(source))
        g = self.describe_target(target, self.neighbours(target))
        return self.align(source, f, target, g)

    # The exported steps of forward, for callers that reuse parts of it: neighbourhoods are the
    # same for a cloud however it is rotated, and a target's descriptors serve every source
    # aligned to it (further network passes, the search's rotation hypotheses).
    def neighbours(self, points: torch.Tensor) -> torch.Tensor:
        """(B, N, 3) -> (B, N, K) neighbour indices: :func:`ball_query` with this network's K and r."""
        return ball_query(points, self.k, self.radius)

    @torch.jit.unused
    def forget_last_call(self) -> None:
        """Drop what the last eager call kept for the training losses (soft partners, B x N x M):
        scripting stores every tensor attribute, so an export would carry them."""
        for name in ("virtual_points", "soft_partners", "overlap_logits"):
            self.__dict__.pop(name, None)

    @torch.jit.export
    def describe_source(self, source: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        """Source descriptors f (B, N, C) from source (B, N, 3) and its neighbours idx (B, N, K)."""
        return self.encoder_p(source, idx)

    @torch.jit.export
    def describe_target(self, target: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        """Target descriptors g (B, M, C) from target (B, M, 3) and its neighbours idx (B, M, K)."""
        return self.encoder_q(target, idx)

    @torch.jit.export
    def align(self, source: torch.Tensor, f: torch.Tensor, target: torch.Tensor, g: torch.Tensor) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """R (B, 3, 3), t (B, 3), w (B, N) from source (B, N, 3) with descriptors f (B, N, C) and
        target (B, M, 3) with g (B, M, C); a target of batch 1 serves all B sources."""
        scores = torch.matmul(f, g.transpose(1, 2)) * torch.exp(-self.log_tau)
        in_overlap: Optional[torch.Tensor] = None
        for head in self.overlap:  # at most one
            logits_s, logits_t = head(source, f, target, g)
            scores = scores + F.logsigmoid(logits_t).unsqueeze(1)  # target points outside the overlap draw less
            in_overlap = torch.sigmoid(logits_s)
            if not torch.jit.is_scripting():
                self.overlap_logits = (logits_s, logits_t)
        W = torch.softmax(scores, dim=-1)
        virtual = torch.matmul(W, target)  # (B, N, 3)
        if not torch.jit.is_scripting():
            self.virtual_points = virtual  # the last eager call's soft partners, for training losses
            self.soft_partners = W
        w = W.amax(dim=-1)  # (B, N)
        if in_overlap is not None:
            w = w * in_overlap
        R, t = weighted_procrustes(source, virtual, w)
        return R, t, w


def count_parameters(module: nn.Module) -> int:
    """Number of distinct trainable parameters (a shared encoder counts once)."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)


def registration_loss(R: torch.Tensor, t: torch.Tensor, R_gt: torch.Tensor, t_gt: torch.Tensor) -> torch.Tensor:
    """The paper's loss: MSE(R, R_gt) + MSE(t, t_gt), over (B, 3, 3) and (B, 3) tensors."""
    return F.mse_loss(R, R_gt) + F.mse_loss(t, t_gt)


def true_places(source: torch.Tensor, R_gt: torch.Tensor, t_gt: torch.Tensor) -> torch.Tensor:
    """Where the source points (B, N, 3) truly lie in the target's frame: R_gt (B, 3, 3) source + t_gt (B, 3)."""
    return torch.matmul(source, R_gt.transpose(1, 2)) + t_gt.unsqueeze(1)


def true_partners(truth: torch.Tensor, target: torch.Tensor, reach: float) -> torch.Tensor:
    """(B, N, M) bool: target point j (target (B, M, 3)) lies within `reach` of source point i's
    true place (truth (B, N, 3), from :func:`true_places`). No gradient flows through it."""
    with torch.no_grad():
        return torch.cdist(truth, target) < reach


def virtual_point_loss(
    source: torch.Tensor, target: torch.Tensor, virtual: torch.Tensor, R_gt: torch.Tensor, t_gt: torch.Tensor, reach: float = 0.05
) -> torch.Tensor:
    """Mean squared distance from each source point's soft partner to where the point truly lies,
    over the points with a target point within `reach` of that place (partial overlap: the others
    have no partner to find). Supervises the correspondences themselves, which the transform loss
    reaches only through the Procrustes fit; for independently sampled clouds the partner is a
    weighted average of the target points around the true place.

    Args:
        source: (B, N, 3); target: (B, M, 3); virtual: (B, N, 3) soft partners (W @ target).
        R_gt: (B, 3, 3), t_gt: (B, 3) the true transform (target ~ R_gt source + t_gt).
        reach: normalised units.
    Returns:
        () loss (normalised units squared).
    """
    truth = true_places(source, R_gt, t_gt)
    has_partner = true_partners(truth, target, reach).any(dim=-1).to(virtual.dtype)
    error = ((virtual - truth) ** 2).sum(dim=-1)
    return (error * has_partner).sum() / has_partner.sum().clamp(min=1.0)


def match_loss(source: torch.Tensor, target: torch.Tensor, W: torch.Tensor, R_gt: torch.Tensor, t_gt: torch.Tensor, reach: float = 0.06) -> torch.Tensor:
    """Cross-entropy of the soft assignment against the true neighbourhood: the mean over source
    points of -log(sum of W_ij over the target points j within `reach` of where point i truly
    lies), over the points with such a target point. It asks each row of W to put its mass near
    the true partner, so that the soft partners are local averages (a correspondence) rather than
    near-uniform weights whose small first-order term carries the rotation.

    Args:
        source: (B, N, 3); target: (B, M, 3); W: (B, N, M) row-stochastic soft assignment.
        R_gt: (B, 3, 3), t_gt: (B, 3) the true transform (target ~ R_gt source + t_gt).
        reach: normalised units.
    Returns:
        () loss (nats).
    """
    near = true_partners(true_places(source, R_gt, t_gt), target, reach).to(W.dtype)  # (B, N, M)
    has_partner = near.amax(dim=-1)
    mass = (W * near).sum(dim=-1).clamp(min=1e-12)
    return -(torch.log(mass) * has_partner).sum() / has_partner.sum().clamp(min=1.0)


# A point with a point of the other cloud within this many median spacings of its true place lies
# in the overlap (:func:`overlap_labels`, benchmarks/network_from_truth.py --overlap-only).
OVERLAP_SPACINGS = 3.0


def median_spacing(points: torch.Tensor) -> torch.Tensor:
    """(B, N, 3) -> (B,) median distance from each point to its nearest other point: the batched
    torch form of :func:`o3dsoft.preprocess.point_spacing`, for labels made on the training device."""
    d = torch.cdist(points, points)
    d.diagonal(dim1=1, dim2=2).fill_(float("inf"))
    return d.amin(dim=-1).median(dim=-1).values


def overlap_labels(
    source: torch.Tensor, target: torch.Tensor, R_gt: torch.Tensor, t_gt: torch.Tensor, spacings: float = OVERLAP_SPACINGS
) -> Tuple[torch.Tensor, torch.Tensor]:
    """Which points lie in the overlap: (B, N) bool, a source point whose true place has a target
    point within `spacings` median target spacings, and (B, M) bool, a target point with a source
    point's true place within `spacings` median source spacings. Spacings, not a fixed distance, so
    that sparse samplings of a surface count as overlapping everywhere."""
    with torch.no_grad():
        truth = true_places(source, R_gt, t_gt)
        d = torch.cdist(truth, target)  # (B, N, M)
        in_s = d.amin(dim=2) < spacings * median_spacing(target).unsqueeze(1)
        in_t = d.amin(dim=1) < spacings * median_spacing(source).unsqueeze(1)
        return in_s, in_t


def overlap_loss(logits: Tuple[torch.Tensor, torch.Tensor], labels: Tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
    """Binary cross-entropy (nats, lower is better) of the overlap head's logits ((B, N), (B, M))
    against :func:`overlap_labels`, the mean over the source's points plus the target's."""
    return sum(F.binary_cross_entropy_with_logits(x, y.to(x.dtype)) for x, y in zip(logits, labels))
