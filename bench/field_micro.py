"""Micro-benchmark: one mapping step (render + MSE + backward + Adam) per field kind.

Side by side in one process, for a batch of ``--rays`` x ``--samples`` (default
4096 x 64): CP, VM, MLP (iMAP-like), dense grid, all with the default renderer
(colour only where the weight matters), plus CP with colour evaluated everywhere.
Every field is first fitted (a few Adam steps on its density only) to the same
scene, an opaque slab across the box, so that the weight distribution along the
rays is realistic (most samples empty, a few at the surface); the fraction of
samples that get a colour evaluation is reported.

Prints min and median wall time over ``--repeats`` and writes
``bench/results/field_micro.json``. Timings on a shared CPU are noisy.

    PYTHONPATH=. .venv/bin/python bench/field_micro.py --threads 1
"""
from __future__ import annotations

import argparse
import json
import platform
import statistics
import time
from pathlib import Path

import torch

from fmapping.field import FieldConfig, build_field
from fmapping.render import render_rays
from fmapping.sampling import ray_aabb, stratified

AABB = torch.tensor([[-2.0, -2.0, -2.0], [2.0, 2.0, 2.0]])


def slab_target(xyz: torch.Tensor) -> torch.Tensor:
    """Pre-activation of an opaque slab 0.2 m thick at z = 0.3 (raw 40 -> sigma ~ 30 / m)."""
    return torch.where((xyz[:, 2] - 0.3).abs() < 0.1, 40.0, 0.0)


def fit_scene(field, steps: int, gen: torch.Generator) -> None:
    """Make ``field``'s density the slab: set directly on the nodes of a dense grid, else a
    short Adam regression of ``density_raw`` (factor lines / planes, or the whole MLP)."""
    if hasattr(field, "density_grid"):
        r = field.density_grid.shape[-1]
        z = torch.linspace(float(AABB[0, 2]), float(AABB[1, 2]), r)
        col = slab_target(torch.stack([torch.zeros_like(z), torch.zeros_like(z), z], -1))
        with torch.no_grad():
            field.density_grid.copy_(col.view(1, 1, r, 1, 1).expand_as(field.density_grid))
        return
    grid = field.grid_parameters()
    opt = torch.optim.Adam(grid or field.decoder_parameters(), lr=0.02 if grid else 5e-3)
    for _ in range(steps if grid else 3 * steps):
        x = torch.rand(16384, 3, generator=gen) * 4 - 2
        x[:4096, 2] = torch.rand(4096, generator=gen) * 0.4 + 0.1  # oversample around the slab
        loss = (field.density_raw(x) - slab_target(x)).pow(2).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()


def make_rays(n_rays: int, n_samples: int, gen: torch.Generator):
    origins = torch.tensor([[0.0, 0.0, -3.0]]).expand(n_rays, 3).contiguous()
    dirs = torch.cat([(torch.rand(n_rays, 2, generator=gen) - 0.5) * 1.0, torch.ones(n_rays, 1)], -1)
    near, far, _ = ray_aabb(origins, dirs, AABB)
    t = stratified(near, far, n_samples, generator=gen)
    target = torch.rand(n_rays, 3, generator=gen)
    return origins, dirs, t, target


def time_steps(field, rays, threshold, repeats: int, warmup: int = 2):
    origins, dirs, t, target = rays
    opt = torch.optim.Adam([
        {"params": field.grid_parameters(), "lr": 0.02},
        {"params": field.decoder_parameters(), "lr": 1e-3},
    ])
    times, frac = [], 0.0
    for i in range(warmup + repeats):
        t0 = time.perf_counter()
        out = render_rays(field, origins, dirs, t, background=0.0, color_weight_threshold=threshold)
        loss = (out.rgb - target).pow(2).mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        dt = time.perf_counter() - t0
        if i >= warmup:
            times.append(dt)
        if threshold is not None:
            w = out.weights.detach()
            frac = float((w > threshold * w.amax(-1, keepdim=True)).float().mean())
        else:
            frac = 1.0
    return times, frac


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rays", type=int, default=4096)
    ap.add_argument("--samples", type=int, default=64)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--fit-steps", type=int, default=60)
    ap.add_argument("--kinds", default="cp,cp_color_everywhere,vm,mlp,grid")
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent / "results" / "field_micro.json"))
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    gen = torch.Generator().manual_seed(0)
    rays = make_rays(a.rays, a.samples, gen)
    n_pts = a.rays * a.samples
    results = {}
    print(f"{a.rays} rays x {a.samples} samples, {a.threads} thread(s), torch {torch.__version__}")
    print(f"{'variant':22s} {'params':>9s} {'flops/pt':>9s} {'colored':>8s} {'min s':>8s} {'median s':>9s} "
          f"{'us/sample':>10s}")
    for variant in a.kinds.split(","):
        kind = variant.split("_")[0]
        threshold = None if variant.endswith("color_everywhere") else 1e-4
        field = build_field(FieldConfig(kind=kind), AABB)
        fit_scene(field, a.fit_steps, torch.Generator().manual_seed(1))
        times, frac = time_steps(field, rays, threshold, a.repeats)
        r = {
            "kind": kind,
            "color_weight_threshold": threshold,
            "params": field.num_parameters(),
            "flops_per_point": field.flops_per_point(),
            "colored_fraction": frac,
            "min_s": min(times),
            "median_s": statistics.median(times),
            "us_per_sample_min": min(times) / n_pts * 1e6,
            "times_s": times,
        }
        results[variant] = r
        print(f"{variant:22s} {r['params']:9d} {r['flops_per_point']:9d} {frac:8.3f} {r['min_s']:8.3f} "
              f"{r['median_s']:9.3f} {r['us_per_sample_min']:10.3f}")
    report = {
        "rays": a.rays, "samples": a.samples, "threads": a.threads, "repeats": a.repeats,
        "torch": torch.__version__, "machine": platform.machine(), "processor": platform.processor(),
        "note": "forward+backward+Adam step of render_rays + MSE; shared CPU, timings are noisy",
        "results": results,
    }
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2))
    print(f"wrote {out}")
    return report


if __name__ == "__main__":
    main()
