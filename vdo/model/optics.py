"""The lens's blur before the pixel: diffraction at the f-number and defocus, as an MTF.

All lengths on the sensor are in metres, spatial frequencies q in cycles per metre on the sensor
(or cycles per pixel where a function says so: q_px = q p, p the pixel pitch).

Diffraction (incoherent light, circular aperture, aberration-free). The working f-number of a lens
focused at s with focal length f is N_w = N (1 + m), m = f / (s - f) the magnification. The MTF is

    MTF_diff(q) = (2/π) [acos ν - ν sqrt(1 - ν²)],   ν = q λ N_w   (0 for ν >= 1),

the Airy pattern's first zero lies at 1.22 λ N_w, and a Gaussian of standard deviation
σ_diff = 0.42 λ N_w per axis fits the Airy core (`AIRY_GAUSS`): at λ = 0.55 µm and N = 8,
σ ≈ 1.85 µm, half of a 3.45 µm pixel.

Defocus (geometric optics). A point at depth Z (along the optical axis) images as a uniform disc of
diameter (the circle of confusion)

    c(Z) = (f / N) f |Z - s| / (Z (s - f))

on the sensor: the depth of field of `vdo.physics.checks.depth_of_field` is where c(Z) <= c_max.
The disc's MTF is 2 J1(π c q) / (π c q) and its standard deviation per axis is c / 4 (a uniform disc
of radius R has <x²> = R² / 4).

The optics' blur is the product of the two MTFs (`OpticsBlur.mtf`); its Gaussian equivalent has
σ_optics² = σ_diff² + (c / 4)² (the variances of the two independent blurs add), used where a blur
must be one number (the blur of a rendered image, `OpticsBlur.sigma_px`).

Without an f-number in the configuration the lens's aperture is unknown; the prediction then
assumes `DEFAULT_F_NUMBER` (diffraction only, in focus), the aperture a DIC lab typically works at.

Light gathered. The photons a pixel collects from a surface of given radiance scale with the
exposure time t and with the aperture's area, (f / N)^2 over a pixel's solid angle f^-2, i.e.
with t / N^2. The sensor's photons_per_unit is stated at the reference exposure t_ref ([sensor]
exposure_ms) and f/`DEFAULT_F_NUMBER`; a camera at (N, t) gathers

    k = (t / t_ref) (DEFAULT_F_NUMBER / N)^2

times as many (`exposure_factor`; working f-number effects on the light, (1 + m)^-2, are below
1 % at the magnifications of DIC lenses, m < 0.05, and ignored).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import j1

__all__ = ["WAVELENGTH_M", "AIRY_GAUSS", "DEFAULT_F_NUMBER", "OpticsBlur", "working_f_number",
           "circle_of_confusion", "diffraction_mtf", "defocus_mtf", "gaussian_mtf", "optics_blur",
           "exposure_factor"]

WAVELENGTH_M = 0.55e-6     # green light, the peak of a monochrome sensor's response under white LEDs
AIRY_GAUSS = 0.42          # σ of the Gaussian fit to the Airy core, in units of λ N
DEFAULT_F_NUMBER = 8.0     # assumed aperture when a camera has no f_number (common DIC practice)


def exposure_factor(f_number: float | None, exposure_s: float | None, reference_s: float) -> float:
    """k = (t / t_ref) (DEFAULT_F_NUMBER / N)^2 (module docstring): the light a camera at f-number N
    and exposure time t (s) gathers relative to the sensor's reference exposure t_ref (s) at
    f/DEFAULT_F_NUMBER. N None: f/DEFAULT_F_NUMBER; t None: t_ref."""
    n = DEFAULT_F_NUMBER if f_number is None else float(f_number)
    t = reference_s if exposure_s is None else float(exposure_s)
    return (t / reference_s) * (DEFAULT_F_NUMBER / n) ** 2


def working_f_number(f_number: float, focal: float, focus: float | None) -> float:
    """N_w = N (1 + m), m = f / (s - f) the magnification at the focus distance s (N if s is None)."""
    if focus is None or focus <= focal:
        return float(f_number)
    return float(f_number) * (1.0 + focal / (focus - focal))


def circle_of_confusion(focal: float, f_number: float, focus: float, depth) -> np.ndarray:
    """Diameter c(Z) [m] on the sensor of the defocus disc of a point at depth Z [m] (module
    docstring): (f / N) f |Z - s| / (Z (s - f))."""
    z = np.asarray(depth, dtype=float)
    return (focal / f_number) * focal * np.abs(z - focus) / (z * (focus - focal))


def diffraction_mtf(q, wavelength: float, f_number: float) -> np.ndarray:
    """MTF of a diffraction-limited circular aperture at q cycles/m on the sensor (module docstring)."""
    nu = np.clip(np.abs(np.asarray(q, dtype=float)) * wavelength * f_number, 0.0, 1.0)
    return (2.0 / np.pi) * (np.arccos(nu) - nu * np.sqrt(1.0 - nu * nu))


def defocus_mtf(q, diameter) -> np.ndarray:
    """MTF 2 J1(π c q) / (π c q) of a uniform disc of diameter c (q and c in reciprocal units)."""
    x = np.pi * np.abs(np.asarray(q, dtype=float)) * np.asarray(diameter, dtype=float)
    safe = np.where(x > 0, x, 1.0)
    return np.where(x > 0, 2.0 * j1(safe) / safe, 1.0)


def gaussian_mtf(q, sigma) -> np.ndarray:
    """exp(-2 π² σ² q²): the transfer function of a Gaussian blur of std σ (q in 1/σ's unit)."""
    q = np.asarray(q, dtype=float)
    return np.exp(-2.0 * np.pi ** 2 * np.asarray(sigma, dtype=float) ** 2 * q * q)


@dataclass(frozen=True)
class OpticsBlur:
    """One camera's optical blur in pixels of that camera.

    airy_px     λ N_w / p: the diffraction scale in pixels (the MTF's cut-off is 1 / airy_px
                cycles per pixel; 0: no diffraction, a pinhole)
    defocus_px  c / p: the defocus disc's diameter in pixels (0: in focus)
    f_number    N, for the record (None: a pinhole)
    assumed     True when N is `DEFAULT_F_NUMBER` because the camera has no f_number
    """

    airy_px: float = 0.0
    defocus_px: float = 0.0
    f_number: float | None = None
    assumed: bool = False

    @property
    def sigma_px(self) -> float:
        """The Gaussian equivalent's std in pixels: sqrt((0.42 λN/p)² + (c / 4p)²)."""
        return math.hypot(AIRY_GAUSS * self.airy_px, 0.25 * self.defocus_px)

    def mtf(self, q_px) -> np.ndarray:
        """The optics' MTF at radial frequencies q_px (cycles per pixel): diffraction x defocus."""
        q = np.abs(np.asarray(q_px, dtype=float))
        out = np.ones_like(q)
        if self.airy_px > 0:
            out = out * diffraction_mtf(q, self.airy_px, 1.0)
        if self.defocus_px > 0:
            out = out * defocus_mtf(q, self.defocus_px)
        return out


def optics_blur(pixel_size: float, focal: float, f_number: float | None, focus: float | None,
                depth: float | None = None, wavelength: float = WAVELENGTH_M) -> OpticsBlur:
    """A camera's `OpticsBlur` for a point at `depth` [m] along its axis: diffraction at the
    working f-number and, when the lens has a focus distance and `depth` is given, the defocus disc
    c(depth). f_number None: `DEFAULT_F_NUMBER` assumed, in focus (flagged `assumed`)."""
    assumed = f_number is None
    n = DEFAULT_F_NUMBER if assumed else float(f_number)
    n_w = working_f_number(n, focal, focus)
    defocus = 0.0
    if not assumed and focus is not None and depth is not None:
        defocus = float(circle_of_confusion(focal, n, focus, depth)) / pixel_size
    return OpticsBlur(airy_px=wavelength * n_w / pixel_size, defocus_px=defocus, f_number=n,
                      assumed=assumed)
