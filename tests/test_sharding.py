"""Sharded batches across (simulated) devices give exactly the unsharded numbers."""

import os
import subprocess
import sys
import textwrap

import pytest

SCRIPT = textwrap.dedent(
    """
    import jax, jax.numpy as jnp, numpy as np
    jax.config.update("jax_enable_x64", True)
    import jaxspring as js
    assert jax.device_count() == 4, jax.devices()
    scene = js.load_scene("cloth")
    ks = jnp.linspace(3000.0, 7000.0, 8)
    run = jax.jit(jax.vmap(lambda k: js.rollout(scene.model, scene.params.replace(ks=k), scene.state, 60, 20).x))
    plain = np.asarray(run(ks))
    sharded_ks = js.sim.shard_batch(ks)
    assert len(sharded_ks.sharding.device_set) == 4
    sharded = run(sharded_ks)
    assert len(sharded.sharding.device_set) == 4
    # each device runs a batch of 2: bit for bit what one device gives for those batches of 2
    per_device = np.concatenate([np.asarray(run(ks[i : i + 2])) for i in range(0, 8, 2)])
    np.testing.assert_array_equal(np.asarray(sharded), per_device)
    # XLA vectorises a batch of 8 differently from one of 2: round-off only
    np.testing.assert_allclose(np.asarray(sharded), plain, rtol=1e-12, atol=1e-12)
    # multi-start fit: members split over the devices, same answers as one device
    chain = js.load_scene("chain")
    obs = js.synthetic_observations(chain, {"ks": 1000.0, "kd": 5.0}, 200, 20)
    inits = [{"ks": k, "kd": d} for k, d in [(400.0, 2.0), (2500.0, 12.0), (700.0, 9.0), (1600.0, 3.0)]]
    results = js.fit_batch(chain, [obs], ["ks", "kd"], inits, iterations=15, identify=False)
    with jax.default_device(jax.devices()[0]):
        single = [js.fit(chain, obs, ["ks", "kd"], i, iterations=15, identify=False) for i in inits]
    for r, s in zip(results, single):
        for n in ("ks", "kd"):
            assert abs(float(r.final[n]) - float(s.final[n])) <= 1e-9 * abs(float(s.final[n])), (n, r.final, s.final)
    print("SHARDED-OK")
    """
)


@pytest.mark.slow
def test_sharded_batches_match_on_four_cpu_devices():
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4", JAX_PLATFORMS="cpu")
    done = subprocess.run([sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "SHARDED-OK" in done.stdout
