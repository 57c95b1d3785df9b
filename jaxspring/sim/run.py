"""Long rollouts for the command line: chunks, a progress bar, blow-up checks, timings."""

from __future__ import annotations

import dataclasses
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from .rollout import energy, frame_count, simulate
from .scene import Scene
from .stability import (
    BlowUp,
    StabilityEstimate,
    energy_threshold,
    estimate_stability,
    first_bad_frame,
    locate_blowup,
)
from .state import State, Trajectory

CHUNK_STEPS = 2000


@dataclasses.dataclass(frozen=True)
class RunResult:
    """A finished (or stopped) run: the frames, timings and stability findings.

    Attributes:
        trajectory: frames up to the end, or up to the last good frame after a blow-up.
        steps: time steps simulated.
        compile_s: time to compile the chunk function [s].
        wall_s: time spent simulating, compile excluded [s].
        energy_start, energy_end: total energy [J] of the first and last frame.
        stability: the scene's stable-dt estimate.
        blowup: where the run blew up, or None.
    """

    trajectory: Trajectory
    steps: int
    compile_s: float
    wall_s: float
    energy_start: float
    energy_end: float
    stability: StabilityEstimate
    blowup: BlowUp | None

    @property
    def steps_per_second(self) -> float:
        return self.steps / self.wall_s if self.wall_s > 0 else float("inf")


def run_scene(
    scene: Scene,
    steps: int,
    save_every: int,
    show_progress: bool = True,
    label: str | None = None,
    stability: StabilityEstimate | None = None,
) -> RunResult:
    """Roll a scene out in chunks with a progress bar, checking for blow-up after each chunk.

    Example:
        >>> result = run_scene(js.load_scene("cloth"), steps=2500, save_every=25)
        >>> result.steps_per_second
    """
    from tqdm.auto import tqdm

    model, params, state = scene.model, scene.params, scene.state
    frames = frame_count(steps, save_every)
    stability = stability or estimate_stability(model, params, state)
    threshold = energy_threshold(model, params, state)
    per_chunk = max(1, min(frames, CHUNK_STEPS // save_every)) if frames else 0
    compiled, compile_s = {}, 0.0

    def compiled_for(n: int):
        nonlocal compile_s
        if n not in compiled:
            start = time.perf_counter()
            compiled[n] = simulate.lower(model, params, state, frames=n, save_every=save_every).compile()
            compile_s += time.perf_counter() - start
        return compiled[n]

    xs, vs = [np.asarray(state.x)[None]], [np.asarray(state.v)[None]]
    blowup, done, wall = None, 0, 0.0
    bar = tqdm(
        total=steps,
        unit="step",
        unit_scale=True,
        desc=label or scene.name,
        file=sys.stderr,
        disable=not show_progress or not sys.stderr.isatty(),
        leave=False,
    )
    current = state
    with bar:
        while done < frames:
            n = min(per_chunk, frames - done)
            chunk = compiled_for(n)  # compile outside the timed region
            start = time.perf_counter()
            end, x, v = chunk(model, params, current)
            jax.block_until_ready(x)
            wall += time.perf_counter() - start
            x, v = np.asarray(x), np.asarray(v)
            bad = first_bad_frame(model, params, x, v, threshold)
            if bad is not None:
                # from the start, step by step: the first bad step whatever save_every is
                blowup = locate_blowup(model, params, state, 0, (done + bad + 1) * save_every, threshold, stability)
                xs.append(x[:bad])
                vs.append(v[:bad])
                done += bad
                break
            xs.append(x)
            vs.append(v)
            done += n
            current = end
            bar.update(n * save_every)
    x_all, v_all = np.concatenate(xs), np.concatenate(vs)
    trajectory = Trajectory(
        x=jnp.asarray(x_all),
        v=jnp.asarray(v_all),
        t=jnp.asarray(np.arange(x_all.shape[0]) * save_every * model.dt, dtype=x_all.dtype),
    )
    e_start = float(energy(model, params, State(x=x_all[0], v=v_all[0])))
    e_end = float(energy(model, params, State(x=x_all[-1], v=v_all[-1])))
    return RunResult(trajectory, done * save_every, compile_s, wall, e_start, e_end, stability, blowup)
