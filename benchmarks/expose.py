"""The sensor's exposure of a full-size image (`SensorModel.expose`) against the one-stream draw
it replaced, in one run.

A 6000 x 4000 linear image (uniform in [0, 0.5] of the default sensor's unit, ~0-17,500 mean
electrons) is exposed by `SensorModel.expose` (blocks of EXPOSE_BLOCK_PIXELS, each with its own
stream, on the process's cores) and by the baseline: the same steps on the whole image at once
from one stream (one Poisson field, then one normal field). Reports the seconds of each (median
of --repeats) and the normalised residual (DN - mean_dn) / sqrt(variance_dn) of both (mean 0,
std 1 for the model's noise).
Run: .venv/bin/python benchmarks/expose.py [--pixels 6000 4000] [--repeats 3]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import numpy as np

from vdo.model.sensor import SensorModel


def one_stream(sensor: SensorModel, linear: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The baseline: the exposure's steps on the whole image from one stream."""
    lam = sensor.quantum_efficiency * sensor.photon_scale * np.maximum(np.asarray(linear, float), 0.0)
    lam = np.minimum(lam, 2.0 * sensor.full_well_e + 40.0 * sensor.read_noise_e + 1000.0)
    electrons = rng.poisson(lam) + rng.normal(0.0, sensor.read_noise_e, size=lam.shape)
    electrons = np.minimum(electrons, sensor.full_well_e)
    return np.clip(np.rint(electrons * sensor.gain + sensor.offset), 0, sensor.max_dn).astype(np.uint16)


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--pixels", type=int, nargs=2, default=(6000, 4000))
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    sensor = SensorModel()
    w, h = args.pixels
    linear = (np.random.default_rng(0).random((h, w)) * 0.5).astype(np.float32)
    mean = sensor.mean_dn(linear.astype(np.float64))
    scale = np.sqrt(sensor.variance_dn(mean))
    threads = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    print(f"{w} x {h} px, {threads} cores, load average {os.getloadavg()[0]:.1f}")
    for label, expose in (("one stream (baseline)", lambda r: one_stream(sensor, linear, r)),
                          ("SensorModel.expose", lambda r: sensor.expose(linear, r))):
        times, dn = [], None
        for k in range(args.repeats):
            t0 = time.perf_counter()
            dn = expose(np.random.default_rng(k))
            times.append(time.perf_counter() - t0)
        r = (dn - mean) / scale
        print(f"{label:<24} {statistics.median(times):6.2f} s (min {min(times):.2f}); residual "
              f"mean {r.mean():+.4f}, std {r.std():.4f}")


if __name__ == "__main__":
    main()
