"""``tactile-slam simulate``: render a synthetic episode with ground truth."""

from __future__ import annotations

import time

from tactile_slam.cli.arguments import output_folder
from tactile_slam.cli.devices import add_device_argument
from tactile_slam.config import load_config
from tactile_slam.sim.episode import LEVELS, SimulationSettings, simulate_episode
from tactile_slam.sim.motions import DEFAULT_FRAMES, KINDS
from tactile_slam.sim.objects import OBJECTS


def register(sub) -> None:
    p = sub.add_parser("simulate", help="render a synthetic GelSight episode with ground-truth poses and shape")
    p.add_argument("--object", default="seed",
                   help=f"catalogue object ({', '.join(sorted(OBJECTS))}) or a PLY/OBJ/STL mesh file")
    p.add_argument("--kind", default="tracking", choices=KINDS,
                   help="tracking (continuous contact), contact_loss (25 of every 100 frames lifted), "
                        "scan (hand-held touches covering the object), long (>= 10000 frames)")
    p.add_argument("--seed", type=int, default=0, help="seeds texture, motion and image noise")
    p.add_argument("--frames", type=int, default=None,
                   help="frames including the 10 contact-free lead-in frames (default: "
                        + ", ".join(f"{k} {v}" for k, v in DEFAULT_FRAMES.items()) + ")")
    p.add_argument("--level", default="gradients", choices=LEVELS,
                   help="gradients: ground-truth maps only; image: also the BGR video (needs the colour model)")
    p.add_argument("--size-mm", type=float, default=None,
                   help="object size, longest dimension (catalogue objects only; default: the catalogue's)")
    p.add_argument("--mesh-scale", type=float, default=None,
                   help="mesh file units to metres, e.g. 1e-3 for mm (mesh files only; default: 1, metres)")
    p.add_argument("--noise", type=float, default=1.0, help="image noise std in grey levels")
    p.add_argument("--colour-model", default=None, help="forward colour model (.pt)")
    p.add_argument("--background", default=None, help="background image (default: real Mini background or synthetic)")
    p.add_argument("--config", default=None, help="sensor preset name or config YAML")
    add_device_argument(p, "device of the rendered maps (cpu, cuda, auto)")
    p.add_argument("--out", required=True, type=output_folder, help="output episode folder")
    p.set_defaults(func=run)


def run(args) -> int:
    settings = SimulationSettings(
        object=args.object, kind=args.kind, seed=args.seed, frames=args.frames, level=args.level,
        size_mm=args.size_mm, mesh_scale=args.mesh_scale, noise_std=args.noise,
        colour_model=args.colour_model, background=args.background,
    )
    t0 = time.perf_counter()
    out = simulate_episode(args.out, settings, load_config(args.config), device=args.device)
    print(f"wrote {args.kind} episode of {args.object} to {out} in {time.perf_counter() - t0:.1f} s")
    return 0
