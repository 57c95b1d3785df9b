"""`jaxspring check`: linearised stability of a scene."""

from __future__ import annotations

import sys

from .common import INTEGRATOR_HELP, TRIAL_STEPS, instability_advice, prepare_scene, refuse_overflowing


def add_parser(sub):
    parser = sub.add_parser(
        "check", help="estimate omega_max and every integrator's stable dt; exit 1 if the scene's would blow up"
    )
    parser.add_argument("scene", help="scene TOML file, or a built-in name")
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE", help="override a parameter")
    parser.add_argument("--integrator", metavar="NAME", help=INTEGRATOR_HELP)
    parser.add_argument("--dt", type=float, help="time step [s] (default: the scene's)")
    parser.add_argument(
        "--dtype", choices=["float32", "float64"], default="float64", help="precision (default float64)"
    )


def command(args):
    from ..errors import BlowUpError
    from ..sim.run import run_scene
    from ..sim.stability import estimate_stability

    scene, _, _ = prepare_scene(args)
    stability = estimate_stability(scene.model, scene.params, scene.state)
    m = scene.model
    refuse_overflowing(scene, stability)
    print(
        f"{scene.name}: {m.particle_count} particles, {m.spring_count} springs, terms {', '.join(m.terms)}; "
        f"dt {m.dt:g} s, integrator {m.integrator}"
    )
    print(
        f"linearised at the initial state{' with every particle in ground contact' if m.has('ground') else ''}: "
        f"omega_max {stability.omega_max:.4g} rad/s, damping rate {stability.damping_max:.4g} 1/s"
    )
    print(stability.table())
    if stability.margin < 1:
        print(f"jaxspring: warning: {instability_advice(scene, stability)}", file=sys.stderr)
        return 1
    trial = run_scene(scene, TRIAL_STEPS, 1, show_progress=False, stability=stability)
    if trial.blowup is not None:
        raise BlowUpError(f"{scene.name}: {trial.blowup.describe()} (a trial run of {TRIAL_STEPS} steps)")
    print(f"ok: {m.integrator} at dt {m.dt:g} s is within its stable dt (margin {stability.margin:.3g}x)")
    return 0
