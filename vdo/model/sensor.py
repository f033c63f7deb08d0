"""EMVA 1288-style camera sensor: renderer radiance -> photons -> electrons -> digital numbers.

The renderer produces a *linear* image (no gamma): a float per pixel proportional to the radiance
reaching that pixel during the configured exposure. `SensorModel` turns it into the digital numbers
(DN) a machine-vision camera would store, following the linear camera model of EMVA 1288:

    photons    mu_p = linear * photons_per_unit                    [photons / pixel]
    electrons  n_e  = Poisson(QE * mu_p) + Normal(0, read_noise_e)  [e-]  (shot + read noise)
               n_e  <- min(n_e, full_well_e)                       (saturation)
    output     DN   = clip(round(K * n_e + offset_dn), 0, 2**bit_depth - 1)

with K = gain in DN per electron. The noise-free mean and the temporal variance are

    mu_DN      = K * QE * mu_p + offset_dn
    sigma2_DN  = K * (mu_DN - offset_dn) + K**2 * read_noise_e**2 + 1/12

(shot noise, read noise, uniform quantisation noise of one DN step). `mean_dn`, `variance_dn` and
`noise_sigma_dn` are written with plain arithmetic only, so they accept NumPy arrays, JAX arrays and
JAX tracers (inside `jax.jit` / `jax.grad`) alike; `noise_sigma_dn` is the per-pixel image noise
used by the DIC uncertainty predictor.

`save_image` writes DN arrays to 8/16-bit PNG or TIFF, the counts in the 16-bit files aligned to
the most significant bits or raw (see its docstring).

Units: electrons (e-), photons, digital numbers (DN, one count of the A/D converter). "Linear" is
the renderer's dimensionless linear radiance value.
"""

from __future__ import annotations

import dataclasses
import numbers
import os
import secrets
from pathlib import Path

import numpy as np

__all__ = ["SensorModel", "save_image"]

MIN_BIT_DEPTH = 8
MAX_BIT_DEPTH = 16
# Default fill: a linear value of 1.0 gives this fraction of the full well (mean electrons).
DEFAULT_FILL_AT_UNIT = 0.7
EXPOSE_BLOCK_PIXELS = 1 << 18   # pixels per block of an exposure, each with its own random stream:
                                # the blocks go to threads; on a 6000 x 4000 image 4-6 s on one
                                # stream, 0.6 s in blocks on 2 cores (benchmarks/README.md)


def _bad(name: str, expected: str, value) -> ValueError:
    return ValueError(f"SensorModel.{name}: expected {expected}, got {value!r}")


def _real(name: str, value, expected: str, ok) -> float:
    """`value` as a finite Python float satisfying `ok`, else ValueError naming the field."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise _bad(name, expected, value)
    value = float(value)
    if not (np.isfinite(value) and ok(value)):
        raise _bad(name, expected, value)
    return value


@dataclasses.dataclass(frozen=True)
class SensorModel:
    """Linear camera sensor (EMVA 1288 model) with shot noise, read noise, saturation, quantisation.

    Fields (a ``None`` default is resolved from the other fields, see the resolved properties
    `gain`, `offset` and `photon_scale`; the field itself keeps ``None`` so that
    ``dataclasses.replace(sensor, bit_depth=16)`` re-derives it):

    quantum_efficiency
        Fraction of photons converted to electrons, in (0, 1]. Dimensionless. Default 0.6.
    full_well_e
        Full-well capacity in electrons (> 0). Electron counts are clipped to it. Default 20000.
    read_noise_e
        Temporal dark (read) noise in electrons rms (>= 0). Default 6.0.
    bit_depth
        A/D converter resolution in bits, an integer in 8..16. The largest DN is
        ``2**bit_depth - 1``. Default 12.
    gain_dn_per_e
        Overall system gain K in DN per electron (> 0). ``None`` (default): chosen so that the
        full well maps exactly to the top DN value, ``K = (2**bit_depth - 1 - offset) /
        full_well_e`` (0.2031 DN/e- for the 12-bit defaults).
    offset_dn
        Dark offset (black level) in DN, in [0, 2**bit_depth - 1). ``None`` (default):
        ``2**(bit_depth - 7)`` DN, i.e. 32 DN at 12 bit, 2 DN at 8 bit, 512 DN at 16 bit (about
        0.8 % of the range, enough that read noise is not clipped at 0 DN).
    photons_per_unit
        Photons per pixel per unit of the renderer's linear value, for the configured exposure
        time and aperture (> 0). ``None`` (default): chosen so that a linear value of 1.0 gives
        70 % of the full well in mean electrons, ``0.7 * full_well_e / quantum_efficiency``
        (23333 photons for the defaults).
    exposure_ms
        The exposure time (ms, > 0) at which `photons_per_unit` holds, with the lens at f/8. A
        camera at another f-number N or exposure time t gathers (t / exposure_ms) (8 / N)^2 times
        as many photons (`vdo.model.optics.exposure_factor`). Default 10 ms.

    Invalid fields raise ValueError naming the field and the expected range.
    """

    quantum_efficiency: float = 0.6
    full_well_e: float = 20000.0
    read_noise_e: float = 6.0
    bit_depth: int = 12
    gain_dn_per_e: float | None = None
    offset_dn: float | None = None
    photons_per_unit: float | None = None
    exposure_ms: float = 10.0

    def __post_init__(self):
        bits = self.bit_depth
        bits_expected = f"an integer in {MIN_BIT_DEPTH}..{MAX_BIT_DEPTH}"
        if isinstance(bits, bool) or not isinstance(bits, numbers.Integral):
            raise _bad("bit_depth", bits_expected, bits)
        if not MIN_BIT_DEPTH <= bits <= MAX_BIT_DEPTH:
            raise _bad("bit_depth", bits_expected, bits)
        top = 2 ** int(bits) - 1
        checks = {
            "quantum_efficiency": ("a number in (0, 1]", lambda v: 0.0 < v <= 1.0),
            "full_well_e": ("a number of electrons > 0", lambda v: v > 0.0),
            "read_noise_e": ("electrons rms >= 0", lambda v: v >= 0.0),
            "gain_dn_per_e": ("None or DN per electron > 0", lambda v: v > 0.0),
            "offset_dn": (f"None or DN in [0, {top})", lambda v: 0.0 <= v < top),
            "photons_per_unit": ("None or photons > 0", lambda v: v > 0.0),
            "exposure_ms": ("milliseconds > 0", lambda v: v > 0.0),
        }
        optional = {"gain_dn_per_e", "offset_dn", "photons_per_unit"}
        # frozen dataclass: normalise (NumPy scalars -> Python numbers) through object.__setattr__
        object.__setattr__(self, "bit_depth", int(bits))
        for name, (expected, ok) in checks.items():
            value = getattr(self, name)
            if value is None and name in optional:
                continue
            object.__setattr__(self, name, _real(name, value, expected, ok))

    # -- resolved parameters -------------------------------------------------------------------

    @property
    def max_dn(self) -> int:
        """Largest digital number, ``2**bit_depth - 1``."""
        return 2**self.bit_depth - 1

    @property
    def offset(self) -> float:
        """Dark offset in DN (`offset_dn`, or its default ``2**(bit_depth - 7)``)."""
        return float(2 ** (self.bit_depth - 7)) if self.offset_dn is None else self.offset_dn

    @property
    def gain(self) -> float:
        """System gain K in DN per electron (`gain_dn_per_e`, or full well -> top DN)."""
        if self.gain_dn_per_e is not None:
            return self.gain_dn_per_e
        return (self.max_dn - self.offset) / self.full_well_e

    @property
    def photon_scale(self) -> float:
        """Photons per pixel per unit linear value (`photons_per_unit`, or 70 % FW at 1.0)."""
        if self.photons_per_unit is not None:
            return self.photons_per_unit
        return DEFAULT_FILL_AT_UNIT * self.full_well_e / self.quantum_efficiency

    # -- model ---------------------------------------------------------------------------------

    def saturation_linear(self) -> float:
        """Linear value whose mean electron count equals the full well (1/0.7 for the defaults).

        Well above it (a few shot-noise sigmas) every pixel is clipped to the full well. If
        `gain_dn_per_e` makes the full well map beyond `max_dn`, the DN output clips earlier, at
        ``(max_dn - offset) / (K QE p)``.
        """
        return self.full_well_e / (self.quantum_efficiency * self.photon_scale)

    @property
    def dn_per_unit(self) -> float:
        """DN per unit of the linear render value above the offset, ``K * QE * photons_per_unit``."""
        return self.gain * self.quantum_efficiency * self.photon_scale

    def mean_dn(self, linear):
        """Noise-free expected DN, ``K * QE * photons_per_unit * linear + offset``.

        Before quantisation and before any clipping (saturation, 0 DN). Plain arithmetic only:
        works on Python floats, NumPy arrays, JAX arrays and JAX tracers.
        """
        if isinstance(linear, (list, tuple)):
            linear = np.asarray(linear, dtype=np.float64)
        return linear * self.dn_per_unit + self.offset

    def variance_dn(self, mean_dn):
        """Temporal noise variance in DN**2 at mean `mean_dn` (EMVA 1288 linear model).

        ``K * (mean_dn - offset) + K**2 * read_noise_e**2 + 1/12``: photon shot noise, read noise
        and uniform quantisation noise. The shot term is taken as 0 for ``mean_dn < offset``.

        It ignores saturation (full-well and top-DN clipping, which drive the real variance to 0)
        and clipping at 0 DN; the 1/12 quantisation term is accurate when the noise before
        quantisation is at least about 0.5 DN rms. Plain arithmetic only: NumPy and JAX
        (including tracers) both work.
        """
        if isinstance(mean_dn, (list, tuple)):
            mean_dn = np.asarray(mean_dn, dtype=np.float64)
        k = self.gain
        signal = mean_dn - self.offset
        signal = 0.5 * (signal + abs(signal))  # max(signal, 0) without np/jnp calls
        return k * signal + (k * k * self.read_noise_e**2 + 1.0 / 12.0)

    def noise_sigma_dn(self, linear):
        """Per-pixel temporal noise in DN rms at `linear`: ``sqrt(variance_dn(mean_dn(linear)))``.

        The image noise used by the uncertainty predictor. Ignores saturation (see `variance_dn`).
        NumPy and JAX (jit/grad) compatible.
        """
        return self.variance_dn(self.mean_dn(linear)) ** 0.5

    def expose(self, linear: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """One noisy exposure of the linear image: returns DN, uint8 (8 bit) or uint16 (> 8 bit).

        Steps: photons = linear * photon_scale; electrons = Poisson(QE * photons) +
        Normal(0, read_noise_e); electrons clipped above at full_well_e; DN = clip(round(K *
        electrons + offset), 0, max_dn). Electrons are not clipped below at 0: read noise swings
        the dark signal both ways around the offset (that is what the offset is for), and a clip
        at 0 e- would bias dark pixels by ``K * read_noise_e / sqrt(2 pi)`` (+0.49 DN for the
        defaults) against `mean_dn`; the 0 DN clip still bounds the output. Negative linear
        values are treated as 0 and +inf as saturating; NaN raises ValueError. All randomness
        comes from `rng` (a `numpy.random.Generator`): the image, in C order, is cut into blocks
        of EXPOSE_BLOCK_PIXELS, block k draws from the k-th of `rng.spawn(blocks)` (first its
        Poisson field, then its normal field), and the blocks run on the process's CPU threads
        (`vdo.core.backend.cpu_threads`). So the same seed gives the same image whatever the
        number of threads.
        """
        if not isinstance(rng, np.random.Generator):
            raise TypeError(f"rng: expected a numpy.random.Generator, got {type(rng).__name__}")
        lin = np.asarray(linear)
        if lin.dtype.kind == "f" and np.isnan(lin).any():
            raise ValueError("linear: image contains NaN")
        flat = lin.reshape(-1)
        out = np.empty(flat.shape, dtype=np.uint8 if self.bit_depth <= 8 else np.uint16)
        starts = range(0, max(1, flat.size), EXPOSE_BLOCK_PIXELS)
        streams = rng.spawn(len(starts))
        # Mean electrons far above the full well saturate anyway; capping keeps rng.poisson valid
        # for huge or infinite inputs and does not change the distribution of what survives.
        cap = 2.0 * self.full_well_e + 40.0 * self.read_noise_e + 1000.0

        def block(k: int) -> None:
            part = slice(starts[k], starts[k] + EXPOSE_BLOCK_PIXELS)
            lam = np.minimum(self.quantum_efficiency * self.photon_scale
                             * np.maximum(np.asarray(flat[part], dtype=np.float64), 0.0), cap)
            g = streams[k]
            electrons = g.poisson(lam).astype(np.float64)             # first draw: photo-electrons
            electrons += g.normal(0.0, self.read_noise_e, size=lam.shape)   # then read noise
            np.minimum(electrons, self.full_well_e, out=electrons)
            out[part] = np.clip(np.rint(electrons * self.gain + self.offset), 0, self.max_dn)

        from vdo.core.backend import cpu_threads

        threads = min(len(starts), cpu_threads())
        if threads > 1:       # NumPy's generators release the GIL while they fill an array
            from concurrent.futures import ThreadPoolExecutor

            with ThreadPoolExecutor(threads) as pool:
                list(pool.map(block, range(len(starts))))
        else:
            for k in range(len(starts)):
                block(k)
        return out.reshape(lin.shape)


PNG_COMPRESS_LEVEL = 1   # zlib level of written PNGs: on a noisy 1500 x 1000 16-bit image 0.10 s and
                         # 1.53 MB against 1.17 s and 1.40 MB at PIL's default 6 (lossless either way)
_FORMATS = {".png": "PNG", ".tif": "TIFF", ".tiff": "TIFF"}


ALIGNMENTS = ("msb", "raw")


def save_image(path, dn_array, bit_depth: int, alignment: str = "msb") -> Path:
    """Write a greyscale DN image to PNG or TIFF atomically; returns the path written.

    `dn_array` is a 2-D integer array with values in ``0 .. 2**bit_depth - 1``. For ``bit_depth
    <= 8`` the file is 8-bit greyscale, the counts as they are; for 9..16 bits it is 16-bit
    greyscale, and `alignment` says where the counts sit in the 16 bits:

    ``"msb"`` (default)
        most significant bits: value = DN x 2**(16 - bit_depth), a 12-bit count shifted left by
        4 (0..4095 -> 0..65520, steps of 16). This is how machine-vision cameras deliver 12-bit
        data in 16-bit containers (e.g. GenICam Mono12 unpacked by most drivers to MSB-aligned
        Mono16), what most DIC software expects of a 16-bit file, and what an ordinary viewer
        shows with its full brightness. Divide by 2**(16 - bit_depth) to get DN back.
    ``"raw"``
        the counts as they are (a 12-bit image keeps 0..4095 in the 16-bit file and looks black
        in a viewer); for software that is told the camera's bit depth and reads raw counts.

    The format follows the suffix: ``.png``, ``.tif`` / ``.tiff``. The image is written to a
    temporary file in the same folder, flushed to disk, then renamed over `path`, so no
    half-written file is left under `path` if writing fails.
    """
    from PIL import Image

    if alignment not in ALIGNMENTS:
        raise ValueError(f"alignment: expected one of {', '.join(ALIGNMENTS)}, got {alignment!r}")

    path = Path(path)
    fmt = _FORMATS.get(path.suffix.lower())
    if fmt is None:
        raise ValueError(f"{path}: expected a .png, .tif or .tiff file name")
    if (
        isinstance(bit_depth, bool)
        or not isinstance(bit_depth, numbers.Integral)
        or not MIN_BIT_DEPTH <= bit_depth <= MAX_BIT_DEPTH
    ):
        raise ValueError(
            f"bit_depth: expected an integer in {MIN_BIT_DEPTH}..{MAX_BIT_DEPTH}, got {bit_depth!r}"
        )
    arr = np.asarray(dn_array)
    if arr.ndim != 2:
        raise ValueError(f"dn_array: expected a 2-D greyscale image, got shape {arr.shape}")
    if not np.issubdtype(arr.dtype, np.integer):
        raise TypeError(f"dn_array: expected an integer array of DN, got dtype {arr.dtype}")
    top = 2 ** int(bit_depth) - 1
    if arr.size and (arr.min() < 0 or arr.max() > top):
        raise ValueError(
            f"dn_array: values {arr.min()}..{arr.max()} outside 0..{top} for {bit_depth}-bit"
        )
    dtype = np.uint8 if bit_depth <= 8 else np.uint16
    if bit_depth > 8 and alignment == "msb":
        arr = np.asarray(arr, dtype=np.uint32) << (16 - int(bit_depth))
    image = Image.fromarray(np.ascontiguousarray(arr, dtype=dtype))  # mode "L" or "I;16"

    folder = path.parent
    while True:  # exclusive create: umask-respecting permissions, no clash with other writers
        tmp = folder / f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp"
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
            break
        except FileExistsError:
            continue
    try:
        with os.fdopen(fd, "wb") as fh:
            options = {"compress_level": PNG_COMPRESS_LEVEL} if fmt == "PNG" else {}
            image.save(fh, format=fmt, **options)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    return path
