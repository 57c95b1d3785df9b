"""One material fitted by two processes (`jax.distributed` on 127.0.0.1, gloo collectives):
the recordings split across the processes' devices give the fit of one process."""

import json
import os
import socket
import subprocess
import sys
import textwrap

import pytest
from test_recordings_fit import ROPE, make_recordings

import jaxspring as js

WORKER = textwrap.dedent(
    """
    import json, sys
    import jax
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.config.update("jax_enable_x64", True)
    jax.distributed.initialize(coordinator_address=f"127.0.0.1:{sys.argv[2]}", num_processes=2,
                               process_id=int(sys.argv[1]), initialization_timeout=120)
    sys.path.insert(0, TESTS)
    import jaxspring as js
    from jaxspring.fit.recording_loss import target_data
    from test_recordings_fit import ROPE, make_recordings
    assert jax.process_count() == 2 and jax.device_count() == 2 and jax.local_device_count() == 1
    rope = js.scene_from_dict(ROPE)
    target = js.recording_target(rope, make_recordings(rope, 4, 30, noise=5e-4), driven=[0, 5], smooth=3)
    placed = js.sim.shard_batch(target_data(target))["x"]
    assert not placed.is_fully_addressable and len(placed.sharding.device_set) == 2
    result = js.fit(rope, target, ["ks.stretch"], {"ks.stretch": 300.0}, iterations=10, identify=False, starts=1)
    print("RESULT", json.dumps(float(result.final["ks.stretch"])), flush=True)
    jax.distributed.shutdown()
    """
)


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@pytest.mark.slow
def test_two_processes_fit_like_one(tmp_path):
    script = WORKER.replace("TESTS", repr(os.path.dirname(__file__)))
    port = str(_free_port())
    env = dict(os.environ, JAX_PLATFORMS="cpu", XLA_FLAGS="")
    workers = [
        subprocess.Popen(
            [sys.executable, "-c", script, str(rank), port],
            env=env,
            stdout=(tmp_path / f"out{rank}").open("w"),  # files, not pipes: nothing read while the fit below runs
            stderr=(tmp_path / f"err{rank}").open("w"),
        )
        for rank in range(2)
    ]
    try:
        # the fit of one process, computed here while the workers start up and connect
        rope = js.scene_from_dict(ROPE)
        target = js.recording_target(rope, make_recordings(rope, 4, 30, noise=5e-4), driven=[0, 5], smooth=3)
        # starts=1 here and in the workers: no start search (tests/test_search.py tests it; here it keeps the given start)
        fitted = js.fit(rope, target, ["ks.stretch"], {"ks.stretch": 300.0}, iterations=10, identify=False, starts=1)
        alone = float(fitted.final["ks.stretch"])
        for worker in workers:
            worker.wait(timeout=600)
    finally:
        for worker in workers:
            worker.kill()
    outputs = []
    for rank, worker in enumerate(workers):
        out, err = ((tmp_path / f"{kind}{rank}").read_text() for kind in ("out", "err"))
        assert worker.returncode == 0, err[-3000:]
        outputs.append(json.loads(out.split("RESULT", 1)[1].split()[0]))
    assert outputs[0] == outputs[1]
    assert abs(outputs[0] / alone - 1) <= 1e-9, (outputs, alone)
    assert abs(alone / 300.0 - 1) > 0.05  # the fit moved
