"""Benchmark: the tip image of a workspace survey, each chunk on the spheres that reach it against every sphere.

The main job's survey images an indented field of nanoparticles through the tip's
129-offset stencil (``Tip.dilate``): a 3 µm workspace of ``--particles`` spheres of radius
5-50 nm and a 5 x 5 grid of 50 nm indents, along the nominal path of a ``--pixels``²
raster (trace and retrace, 10 % over-scan). Two ways in one run: ``render`` as it is (chunks
of 2048 consecutive samples, each imaged on the spheres that reach its box,
``Indented.imaged``), and the stencil over every sphere point by point (how ``render``
imaged it before). Both jitted; compile time apart, then the median of ``--repeats`` calls;
the largest difference of the two images is printed.

    python experiments/bench_render.py [--pixels 256] [--particles 64] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import matplotlib
import numpy as np
from benchutil import device_label, machine_info, time_jax

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from jaxafm.instrument.afm import Raster, render
from jaxafm.instrument.samples import Indented, Particles, Tip


def field(particles: int, seed: int = 0) -> Indented:
    """Spheres of 5-50 nm over a 3 µm square centred at 0, pressed with a 5 x 5 grid of 50 nm indents."""
    rng = np.random.default_rng(seed)
    spheres = Particles(
        jnp.asarray(rng.uniform(-1500, 1500, (particles, 2))), jnp.asarray(rng.uniform(5, 50, particles))
    )
    sample = Indented.empty(spheres, Tip(), capacity=25)
    press = jax.jit(lambda s, xy: s.press(xy, 50.0))
    for x in np.linspace(-1000, 1000, 5):
        for y in np.linspace(-1000, 1000, 5):
            sample = press(sample, jnp.array([x, y]))
    return sample


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pixels", type=int, default=256)
    ap.add_argument("--particles", type=int, default=64)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", type=Path, default=Path("experiments/results/bench_render"))
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    tip, sample = Tip(), field(a.particles)
    path = jnp.asarray(Raster((3000.0, 3000.0), a.pixels, a.pixels).wanted().reshape(-1, 2))
    every = lambda p: jax.lax.map(lambda q: tip.dilate(sample.height, q), p, batch_size=2048)
    runs = {
        "each chunk on the spheres\nthat reach it (render)": lambda p: render(sample, tip, p),
        "every sphere": every,
    }
    results, images, names = {}, {}, list(runs)
    for name, fn in runs.items():
        results[name], images[name] = time_jax(fn, path, repeats=a.repeats)
        label = name.replace("\n", " ")
        print(f"{label:44s} {results[name]['median_s']:7.3f} s  (compile {results[name]['compile_s']:.1f} s)")
    diff = float(jnp.max(jnp.abs(images["every sphere"] - images[names[0]])))
    ratio = results["every sphere"]["median_s"] / results[names[0]]["median_s"]
    print(f"{path.shape[0]} samples; {ratio:.2f}x faster; largest difference {diff:.2g} nm")
    doc = {"pixels": a.pixels, "particles": a.particles, "samples": int(path.shape[0])}
    doc |= {"speedup": ratio, "max_difference_nm": diff, "runs": results, "machine": machine_info()}
    (a.out / "metrics.json").write_text(json.dumps(doc, indent=1))
    fig, ax = plt.subplots(figsize=(8, 2.8), constrained_layout=True)
    ax.barh(names, [results[n]["median_s"] for n in names], color=["C0", "C7"])
    for i, n in enumerate(names):
        ax.text(results[n]["median_s"], i, f" {results[n]['median_s']:.2f} s", va="center")
    ax.set(
        xlabel=f"seconds per image (median of {a.repeats}, compiled; {device_label(machine_info())})",
        title=f"Tip image of a {a.pixels}² survey ({path.shape[0]:,} samples), {a.particles} spheres, "
        f"25 indents:\n{ratio:.2f}x faster, the same image to {diff:.1g} nm",
        xlim=(0, 1.3 * max(r["median_s"] for r in results.values())),
    )
    fig.savefig(a.out / "bench_render.png", dpi=110)
    print(f"wrote {a.out}/metrics.json, bench_render.png")


if __name__ == "__main__":
    main()
