"""Texture filtering knob: accuracy of the hybrid composite vs pyrender, and its cost.

Run: ``.venv/bin/python benchmarks/bench_texture.py``. For near (0.25 m), mid (0.5 m) and far
(0.8 m) views of the mustard bottle at several polar angles, prints the mean absolute error (in
1/255 units, inside the visible mask) between ``I_adv`` and pyrender's own render of the same
textured object, and the median time of one differentiable texture pass (forward + backward).
"""

from __future__ import annotations

import os
import statistics
import time

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np
import torch
import torch.nn.functional as F


def main() -> None:
    from attack.render import HybridRenderer, render_adversarial
    from sim.geometry import look_at
    from sim.render import SceneRenderer
    from sim.spec import default_scene
    from sim.world import SimWorld

    spec = default_scene()
    size = 128
    r = SceneRenderer(spec, size, size)
    hr = HybridRenderer(r)
    w = SimWorld(spec, image_size=size, seed=0, renderer=r)
    adv = r.face_coded
    c = w.object_center_array[adv]
    g = torch.Generator().manual_seed(0)
    textures = {
        "smooth": (F.interpolate(torch.rand(1, 3, 16, 16, generator=g), size=(256, 256), mode="bilinear")[0] * 255)
        .round()
        .byte()
        .permute(1, 2, 0)
        .numpy(),
        "noise": (np.random.default_rng(0).random((256, 256, 3)) * 255).astype(np.uint8),
    }
    print(f"# {size}x{size} policy image, 256x256 texture; cores={os.cpu_count()} torch={torch.__version__}")
    print(
        "| texture | distance | phi | pixels | MAE bilinear (/255) | MAE trilinear (/255) | ms bilinear fwd+bwd | "
        "ms trilinear fwd+bwd |"
    )
    print("|---|---|---|---|---|---|---|---|")
    for tname, tex in textures.items():
        tt = torch.from_numpy(tex).permute(2, 0, 1).float() / 255.0
        for dist in (0.25, 0.5, 0.8):
            for phi in (10, 45, 80):
                eye = c + dist * np.array([np.sin(np.radians(phi)), 0.1, np.cos(np.radians(phi))])
                T = look_at(eye, c)
                r.set_object_texture(adv, None)
                cap = hr.capture(w, T)
                r.set_object_texture(adv, tex)
                ref = r.render(T, with_ids=False).rgb.astype(np.float64)
                m = cap.fragments.mask()
                row = []
                times = []
                for s in ("bilinear", "trilinear"):
                    img = render_adversarial(cap, tt, s).permute(1, 2, 0).numpy() * 255.0
                    row.append(np.abs(img[m] - ref[m]).mean())
                    ts = []
                    for _ in range(7):
                        x = tt.clone().requires_grad_(True)
                        t0 = time.perf_counter()
                        render_adversarial(cap, x, s).sum().backward()
                        ts.append(1000 * (time.perf_counter() - t0))
                    times.append(statistics.median(ts))
                print(
                    f"| {tname} | {dist} m | {phi} deg | {int(m.sum())} | {row[0]:.2f} | {row[1]:.2f} | {times[0]:.2f} "
                    f"| {times[1]:.2f} |"
                )
    r.set_object_texture(adv, None)
    r.close()


if __name__ == "__main__":
    main()
