"""Riley (riley-raster, pyvale's rasteriser) on a speckled plate, timed: run by
`benchmarks/render.py --riley PYTHON` with the Python of an environment where riley-raster is
installed (not vdo's). It reads a job file (.npz: the speckle tile `texture` in [0, 1], the image
size `pixels`, the texels per pixel `texels_per_px`, the subsample counts `sub_samples` and the
`threads`), renders a frontal plate whose texture is that tile (bilinear texture reads, as vdo's
renders; the tile repeated to cover the view), each subsample count twice (the second timed),
and writes `images` and `seconds` to the output .npz.

    PYTHON benchmarks/riley_plate.py JOB.npz OUT.npz
"""

from __future__ import annotations

import sys
import time

import numpy as np


def main(job_path: str, out_path: str) -> None:
    import riley

    job = np.load(job_path)
    texture = np.ascontiguousarray(job["texture"], dtype=np.float64)[None]      # (1, H_t, W_t)
    width, height = (int(v) for v in job["pixels"])
    texels_per_px = float(job["texels_per_px"])
    threads = int(job["threads"])
    # The plate: the tile repeated to cover the view, 1 m per tile width, so a pixel covers
    # texels_per_px texels.
    reps = (int(np.ceil(height * texels_per_px / texture.shape[1])) + 1,
            int(np.ceil(width * texels_per_px / texture.shape[2])) + 1)
    texture = np.ascontiguousarray(np.tile(texture, (1, *reps)))
    ht, wt = texture.shape[1:]
    wt_tile = wt / reps[1]
    size = np.array([wt, ht]) / wt_tile                # metres
    coords = np.array([[0, 0, 0], [size[0], 0, 0], [size[0], size[1], 0], [0, size[1], 0]], dtype=np.float64)
    coords[:, :2] -= size / 2
    connect = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int64)
    uvs = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=np.float64)
    convention = riley.ConnectConvention(riley.EElemType.TRI3, riley.EConnectAxis.ROW, 0,
                                         riley.ENodeOrder.RILEY)
    shader = riley.TextureShader(uvs=uvs, texture=texture, sample=riley.TextureSample.linear)
    mesh = riley.create_mesh(convention, riley.MeshType.tri3opt, coords, connect, shader)
    pixel_m = texels_per_px / wt_tile                 # metres of plate per pixel
    focal, pitch = 50e-3, 5e-6
    distance = focal * pixel_m / pitch
    images, seconds = [], []
    for sub in (int(s) for s in job["sub_samples"]):
        camera = riley.Camera(pixels_num=(width, height), pixels_size=(pitch, pitch),
                              pos_world=(0.0, 0.0, distance), rot_world=(0.0, 0.0, 0.0),
                              roi_cent_world=(0.0, 0.0, 0.0), focal_length=focal, sub_sample=sub)
        config = riley.RasterConfig(parallel=threads, save_strategy=riley.SaveStrategy.memory, report=0)
        config.save_scaling = riley.ScaleStrategy.none
        riley.raster([mesh], [camera], config)
        t0 = time.perf_counter()
        image = riley.raster([mesh], [camera], config)
        seconds.append(time.perf_counter() - t0)
        images.append(np.asarray(image, dtype=np.float64).reshape(height, width))
    np.savez(out_path, images=np.stack(images), seconds=np.array(seconds))


if __name__ == "__main__":
    main(*sys.argv[1:3])
