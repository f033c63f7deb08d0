"""The list of (camera, sample) pairs the information is summed over.

Sparse pairs (`ViewData`). Most (camera, sample) pairs have w = 0 exactly (occluded, behind, outside
the image, beyond the incidence limit), so the per-pair work runs over a list of P selected pairs only
and is summed per sample with `jax.ops.segment_sum`. The list is laid out camera-major in blocks of
`block` pairs that all belong to one camera (each camera's list padded to whole blocks, the block
count padded to a bucket so that a changing P seldom recompiles): the camera parameters are then
broadcast per block and their gradient is a row sum, not a scatter into C slots (which XLA:CPU
serialises: 40 ms for 10 cameras x 317k pairs against < 1 ms). Padding pairs have occlusion 0,
hence weight and gradient exactly 0. The list carries its pairs' sample geometry (point, normal,
t_u, t_v), copied once when it is built: gathering it from the samples on every call cost ~10 ms.
`ViewData.from_dense` builds the list from (C, N) arrays: without cameras it keeps every pair
with occlusion > 0 (exact for any camera parameters); given the cameras it also drops the pairs
that are behind the camera, outside the image extended by `margin_px`, or beyond the incidence
limit plus `margin_angle` at those cameras. A dropped pair has w = 0 and a zero gradient there, so
value and gradient stay exact as long as no camera moves so far that a dropped pair crosses into
its image or incidence range: refresh the selection when the cameras move by more than the margins
(the optimizer does so between inner solves, with visibility).

`bucket` rounds the block count up to one of few sizes; with a `sizes` dict kept across calls
the count is fixed at the first list's x `PAIR_HEADROOM` instead (`ViewData.from_dense`).

Above `vdo.information.inputs` and `projection` (the sample table; the selection projects in
NumPy with `vdo.model.camera`); below `blocks`. `vdo.objective` re-exports `ViewData`, `bucket` and
`PAIR_HEADROOM`."""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from vdo.information.inputs import CameraParams, Samples, Settings
from vdo.information.projection import sample_table
from vdo.model.camera import image_point, rotation

PAIR_HEADROOM = 1.25   # `ViewData.from_dense` with sizes: the first list's blocks x this, for later layouts


def bucket(n: int) -> int:
    """n rounded up to 2^k x {1, 1.125, ..., 1.875} (at most 12.5 % more): few distinct sizes."""
    if n <= 16:
        return max(n, 1)
    step = 1 << (n.bit_length() - 4)
    return -(-n // step) * step


class ViewData(eqx.Module):
    """Per-pair constants for P selected (camera, sample) pairs (module docstring, "Sparse pairs"):
    camera, sample (P,) int32 indices; occlusion (P,) in [0, 1] from the ray cast (1 = seen);
    contrast c in DN (image = b + c f_hat); noise sigma in DN rms per pixel; geometry
    (12, B, block) the pairs' sample point, normal, t_u and t_v (m, unit), copied from the
    `Samples` it was built with (the per-pair work reads them contiguously instead of gathering
    them per call).

    Layout: P = B x `block`; the pairs of block b (P[b*block:(b+1)*block]) all belong to one camera
    and are sorted by sample; padding pairs have occlusion 0 (and contrast 0, noise 1). The block
    count B is a multiple of `chunk`, the blocks per chunk of both passes. Build it with
    `from_dense`, and score it with the same samples. Pairs not listed have weight 0."""

    camera: jax.Array
    sample: jax.Array
    occlusion: jax.Array
    contrast: jax.Array
    noise: jax.Array
    geometry: jax.Array
    block: int = eqx.field(static=True, default=1)
    chunk: int = eqx.field(static=True, default=1)

    @classmethod
    def from_dense(cls, occlusion, contrast, noise, samples: "Samples",
                   cameras: "CameraParams | None" = None, settings: "Settings | None" = None, *,
                   margin_px: float = 64.0, margin_angle: float = math.radians(3.0),
                   block: int = 1024, chunk_pairs: int = 32768, sizes: dict | None = None) -> "ViewData":
        """Select the pairs that can have w > 0 from (C, N) arrays (contrast, noise broadcast)
        for the N `samples`.

        Without `cameras`: every pair with occlusion > 0 (exact for any camera parameters). With
        them: also in front (Z_c > near), inside the image grown by `margin_px` on every side,
        and incidence below `settings.incidence_limit + margin_angle`: exact at these cameras and
        while they move less than the margins (refresh after larger moves). `block` is the
        most pairs per block, `chunk_pairs` about the pairs per chunk of both passes.

        `sizes` (a dict kept with the samples, e.g. `vdo.state.Geometry.sizes`) fixes the block
        count per block size across calls, so that the lists of new camera layouts keep one
        shape and the programs that read them compile once: the first list sets it to its
        blocks x `PAIR_HEADROOM` (whole chunks); a longer list raises it (one new shape).
        Without it the count is `bucket`ed (a new bucket, a new compile)."""
        occ = np.asarray(occlusion, dtype=np.float64)
        if occ.ndim != 2 or occ.shape[1] != samples.points.shape[0]:
            raise ValueError(f"ViewData.from_dense: occlusion must be (C, N) with N = "
                             f"{samples.points.shape[0]} samples, got {occ.shape}")
        contrast = np.broadcast_to(np.asarray(contrast, dtype=np.float64), occ.shape)
        noise = np.broadcast_to(np.asarray(noise, dtype=np.float64), occ.shape)
        keep = occ > 0
        if cameras is not None:
            keep &= _candidates(cameras, samples, settings or Settings(), margin_px, margin_angle)
        return cls._from_pairs(*np.nonzero(keep), occ, contrast, noise,
                               np.asarray(sample_table(samples)), block, chunk_pairs, sizes)

    @classmethod
    def _from_pairs(cls, cam, smp, occ, contrast, noise, table, block, chunk_pairs, sizes=None):
        """cam, smp (K,) sorted by camera then sample (np.nonzero order); dense (C, N) values;
        table (N, 12) the sample columns (`sample_table`)."""
        n_cameras = occ.shape[0]
        counts = np.bincount(cam, minlength=n_cameras)
        most = int(counts.max()) if counts.size else 0
        L = block if most >= block else max(8, 1 << max(most - 1, 0).bit_length())
        blocks = -(-counts // L)  # per camera
        if sizes is not None and ("blocks", L) in sizes and sizes[("blocks", L)][0] >= blocks.sum():
            n_blocks, chunk = sizes[("blocks", L)]
        else:
            n_blocks = bucket(int(blocks.sum())) if sizes is None else \
                max(1, math.ceil(PAIR_HEADROOM * int(blocks.sum())))
            chunk = max(1, min(chunk_pairs // L, n_blocks))
            n_blocks = -(-n_blocks // chunk) * chunk
            if sizes is not None:
                sizes[("blocks", L)] = (n_blocks, chunk)
        block_cam = np.zeros(n_blocks, dtype=np.int32)
        block_cam[:blocks.sum()] = np.repeat(np.arange(n_cameras), blocks)
        first_pair = np.cumsum(counts) - counts
        first_slot = (np.cumsum(blocks) - blocks) * L
        dest = first_slot[cam] + np.arange(cam.size) - first_pair[cam]
        P = n_blocks * L
        out_s = np.zeros(P, dtype=np.int32)
        out_o, out_c, out_n = np.zeros(P), np.zeros(P), np.ones(P)
        out_s[dest] = smp
        out_o[dest], out_c[dest], out_n[dest] = occ[cam, smp], contrast[cam, smp], noise[cam, smp]
        return cls(jnp.asarray(np.repeat(block_cam, L)), jnp.asarray(out_s), jnp.asarray(out_o),
                   jnp.asarray(out_c), jnp.asarray(out_n),
                   jnp.asarray(table[out_s].T.reshape(12, n_blocks, L)), L, chunk)

    @property
    def n_blocks(self) -> int:
        """B, the number of blocks (pairs = B x `block`)."""
        return self.camera.shape[0] // self.block

    def padded(self, n_blocks: int, chunk: int | None = None) -> "ViewData":
        """This list with padding blocks up to `n_blocks` (>= `n_blocks`, a multiple of `chunk`,
        the result's blocks per chunk, default this list's):
        occlusion 0, hence weight and gradient exactly 0; a real sample's geometry (finite). The
        same values from every program, with the shapes of a larger list: callers fix the size
        so that new layouts reuse one compiled program (`vdo.optimize`, `vdo.physics.predict`)."""
        L, B, chunk = self.block, self.n_blocks, chunk or self.chunk
        if n_blocks < B or n_blocks % chunk:
            raise ValueError(f"ViewData.padded: {n_blocks} blocks must be >= {B} and a multiple of "
                             f"the chunk {chunk}")
        extra = (n_blocks - B) * L   # on the host: an XLA concatenate would compile per shape
        fill = lambda a, value: jnp.asarray(np.concatenate(  # noqa: E731
            [np.asarray(a), np.full(extra, value, np.asarray(a).dtype)]))
        table = np.asarray(self.geometry)
        geometry = jnp.asarray(np.concatenate([table, np.broadcast_to(
            table[:, :1, :1], (12, n_blocks - B, L))], axis=1))
        return ViewData(fill(self.camera, 0), fill(self.sample, 0), fill(self.occlusion, 0.0),
                        fill(self.contrast, 0.0), fill(self.noise, 1.0), geometry, L, chunk)

    @property
    def n_pairs(self) -> int:
        """Number of listed pairs with occlusion > 0 (not counting the padding)."""
        return int(np.count_nonzero(np.asarray(self.occlusion)))


def _candidates(cameras, samples, st, margin_px, margin_angle):
    """(C, N) bool, numpy: in front, inside the image + margin_px, incidence < limit + margin."""
    R = rotation(*(np.asarray(a) for a in (cameras.pan, cameras.tilt, cameras.roll)), xp=np)
    d = np.asarray(samples.points)[None] - np.asarray(cameras.position)[:, None]  # (C, N, 3)
    p = np.einsum("cab,cnb->acn", R, d)
    front = p[2] > st.near
    z = np.where(front, p[2], 1.0)
    f = np.asarray(cameras.focal_px)[:, None]
    dist = (None if cameras.distortion is None else
            tuple(np.asarray(cameras.distortion)[:, k, None] for k in range(5)))
    u, v = image_point((f, None, np.asarray(cameras.cx)[:, None], f, np.asarray(cameras.cy)[:, None]),
                       p[0] / z, p[1] / z, dist)
    W, H = np.asarray(cameras.width)[:, None], np.asarray(cameras.height)[:, None]
    lo = -0.5 - margin_px
    inside = (u > lo) & (u < W - 1 - lo) & (v > lo) & (v < H - 1 - lo)
    cos_lim = math.cos(min(st.incidence_limit + margin_angle, math.pi))
    nd = -np.einsum("nk,cnk->cn", np.asarray(samples.normals), d)
    facing = nd > cos_lim * np.sqrt(np.einsum("cnk,cnk->cn", d, d))
    return front & inside & facing
