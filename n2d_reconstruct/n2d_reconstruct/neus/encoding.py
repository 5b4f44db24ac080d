"""Multi-resolution hash grid encoding (Instant-NGP) in pure PyTorch, with its spatial Jacobian.

Points in [0, 1]^3 are encoded level by level: the level's grid vertices around the point are looked up in a
table (directly for coarse levels whose vertices fit, by a spatial hash for fine ones) and trilinearly
interpolated. The encoding also returns d(encoding)/d(point) computed in closed form from the same corner
features, so an SDF network gets its analytic gradient (normals, eikonal loss) without a double backward
through the table lookup.

CPU speed comes from the layout: one autograd Function gathers all corners with a 1-D `index_select`
(a vertex's features read as one 8-byte word), keeps every intermediate as corner x level x point x feature
slabs (contiguous inner blocks, so elementwise ops vectorise), and folds both outputs' gradients into one
`index_add_` (int64 rows) in a hand-written backward. Hash arithmetic is int32 (wraps modulo 2**32; only the low
bits are kept). `index_add_` with int32 rows of a 2-D table is ~5x slower on CPU.
"""

from __future__ import annotations

import math

import torch
from torch import nn

_PRIMES = (1, 2654435761 - 2**32, 805459861)
"""Instant-NGP's spatial hash primes, one per axis (the second as its int32 bit pattern)."""

_WORD = {1: torch.float32, 2: torch.float64, 4: torch.complex128}
"""Features per vertex that one machine word holds: those tables are gathered as words."""


class _Encode(torch.autograd.Function):
    """(enc, jac) = trilinear(table[corners]) and its d/dx; gradients flow to the table only.

    idx: 2 x 2 x 2 x L x N int32 rows (corner [ix, iy, iz]); frac: 3 x L x N x F (position in the cell,
    repeated per feature); res: L. Returns enc L x N x F and jac 3 x L x N x F (or None).
    The backward adds the table's gradient straight into `table.grad` (allocated once, kept between steps:
    zero it with `zero_grad(set_to_none=False)`), which spares a table-sized allocation and copy per step.
    """

    @staticmethod
    def forward(ctx, table, idx, frac, res, jacobian: bool):
        features = table.shape[1]
        if table.dtype == torch.float32 and features in _WORD:
            flat = table.view(_WORD[features]).view(-1).index_select(0, idx.view(-1)).view(torch.float32)
        else:
            rows = (idx.long() * features)[..., None] + torch.arange(features, device=idx.device)
            flat = table.view(-1).index_select(0, rows.view(-1))
        c = flat.view(*idx.shape, features)  # 2 x 2 x 2 x L x N x F
        fx, fy, fz = frac
        cz = torch.lerp(c[:, :, 0], c[:, :, 1], fz)  # 2 x 2 x L x N x F
        cyz = torch.lerp(cz[:, 0], cz[:, 1], fy)  # 2 x L x N x F
        enc = torch.lerp(cyz[0], cyz[1], fx)
        ctx.save_for_backward(idx, frac, res)
        ctx.table, ctx.jacobian = table, jacobian
        if not jacobian:
            return enc, None
        jac = torch.empty((3, *enc.shape), dtype=enc.dtype, device=enc.device)
        torch.sub(cyz[1], cyz[0], out=jac[0])
        torch.lerp(cz[0, 1] - cz[0, 0], cz[1, 1] - cz[1, 0], fx, out=jac[1])
        dzy = torch.lerp(c[:, 0, 1] - c[:, 0, 0], c[:, 1, 1] - c[:, 1, 0], fy)  # 2 x L x N x F
        torch.lerp(dzy[0], dzy[1], fx, out=jac[2])
        return enc, jac.mul_(res[None, :, None, None])

    @staticmethod
    def backward(ctx, g_enc, g_jac):
        idx, frac, res = ctx.saved_tensors
        table = ctx.table
        fx, fy, fz = frac
        e = torch.zeros_like(fx) if g_enc is None else g_enc
        shape = (2, 2, 2, *fx.shape)
        g = torch.empty(shape, dtype=fx.dtype, device=fx.device)
        p = torch.empty(shape[2:], dtype=fx.dtype, device=fx.device)
        torch.mul(fy, e, out=p[1])  # wy_j e (+ sy_j gy below)
        if ctx.jacobian and g_jac is not None:
            gx, gy, gz = g_jac * res[None, :, None, None]
            p[1].add_(gy)
            torch.sub(e, p[1], out=p[0])  # (1 - fy) e - gy
            q1 = fy * gx  # wy_j gx, j = 1 (j = 0: gx - q1)
            a = torch.empty(shape[:2] + shape[3:], dtype=fx.dtype, device=fx.device)
            torch.addcmul(q1, fx, p[1], out=a[1, 1])  # a[i, j] = wx_i p_j + sx_i q_j
            torch.addcmul(gx - q1, fx, p[0], out=a[1, 0])
            torch.sub(p, a[1], out=a[0])
            w1 = fy * gz
            b = torch.stack([gz - w1, w1])  # wy_j gz
            b = torch.stack([b - fx * b, fx * b])  # wx_i wy_j gz
            torch.addcmul(b, fz, a, out=g[:, :, 1])
            torch.sub(a, g[:, :, 1], out=g[:, :, 0])  # (1 - fz) a - b
        else:
            torch.sub(e, p[1], out=p[0])
            a = torch.stack([p - fx * p, fx * p])
            torch.mul(a, fz, out=g[:, :, 1])
            torch.sub(a, g[:, :, 1], out=g[:, :, 0])
        if table.grad is None:
            table.grad = torch.zeros_like(table)
        table.grad.index_add_(0, idx.view(-1).long(), g.view(-1, table.shape[1]))
        return None, None, None, None, None


class HashGrid(nn.Module):
    """`levels` grids from `base_res` to `max_res` cells per axis, `features` numbers per vertex.

    Every level owns 2**log2_table rows of one flat parameter table. A level whose grid fits its rows is
    indexed densely (strides that are powers of two, so the same XOR formula serves both cases).
    """

    def __init__(self, levels: int, features: int, log2_table: int, base_res: int, max_res: int):
        super().__init__()
        self.levels, self.features, self.table_size = levels, features, 2**log2_table
        growth = math.exp((math.log(max_res) - math.log(base_res)) / max(levels - 1, 1))
        res = [int(math.floor(base_res * growth**level)) for level in range(levels)]
        mult = []
        for r in res:
            bits = max(1, math.ceil(math.log2(r + 2)))
            mult.append((1, 2**bits, 2 ** (2 * bits)) if 3 * bits <= log2_table else _PRIMES)
        self.register_buffer("res", torch.tensor(res, dtype=torch.float32), persistent=False)
        self.register_buffer("mult", torch.tensor(mult, dtype=torch.int32).T.contiguous(), persistent=False)
        offset = torch.arange(levels, dtype=torch.int32) * self.table_size
        self.register_buffer("offset", offset, persistent=False)
        self.table = nn.Parameter(torch.empty(levels * self.table_size, features).uniform_(-1e-4, 1e-4))
        self.resolutions = res

    @property
    def out_dim(self) -> int:
        return self.levels * self.features

    def forward(self, x: torch.Tensor, jacobian: bool = False, level_mask: torch.Tensor | None = None):
        """Encode N x 3 points in [0, 1]: (N x levels*features, or None / levels*features x 3 x N).

        The Jacobian comes transposed (point index last); `contract` turns it into a gradient. `level_mask`
        (levels floats) scales each level's output: coarse-to-fine training switches fine levels on gradually.
        """
        n = x.shape[0]
        pos = x.T.clamp(0.0, 1.0 - 1e-6)[:, None, :] * self.res[None, :, None]  # 3 x L x N
        cell = pos.floor()
        frac = (pos - cell)[..., None].expand(3, self.levels, n, self.features).contiguous()
        lo = cell.int() * self.mult[:, :, None]  # per-axis hash terms of the lower corner (int32, wrapping)
        terms = torch.stack([lo, lo + self.mult[:, :, None]], 1) & (self.table_size - 1)  # 3 x 2 x L x N
        tx = terms[0] | self.offset[None, :, None]  # the level offset lies above the masked bits
        idx = tx[:, None, None] ^ terms[1][None, :, None] ^ terms[2][None, None, :]  # 2 x 2 x 2 x L x N
        enc, jac = _Encode.apply(self.table, idx, frac, self.res, jacobian)
        if level_mask is not None:
            enc = enc * level_mask[:, None, None]
            jac = None if jac is None else jac * level_mask[None, :, None, None]
        enc = enc.permute(1, 0, 2).reshape(n, self.out_dim)
        return enc, None if jac is None else jac.permute(0, 1, 3, 2).reshape(3, self.out_dim, n)

    @staticmethod
    def contract(jac: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """sum_k v[n, k] * d enc_k / d x[n]: N x 3 from the transposed Jacobian and N x levels*features."""
        return (jac * v.T[None]).sum(1).T
