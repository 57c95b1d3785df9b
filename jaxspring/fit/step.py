"""One optimiser step of a stage, batched over the members of a fit with `vmap`."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import optax

from .settings import FitSettings


def _optimizer(settings: FitSettings):
    if settings.optimizer == "lbfgs":
        return optax.lbfgs()
    return optax.chain(optax.clip_by_global_norm(settings.clip), optax.adam(settings.learning_rate))


def _strong(leaf):
    leaf = jnp.asarray(leaf)
    return jax.lax.convert_element_type(leaf, leaf.dtype) if leaf.weak_type else leaf


def step_function(loss, settings: FitSettings, data_batched: bool):
    """(step, init, value) of the optimiser on `loss(theta, data)`, each over the members
    (`data` shared, or one per member with `data_batched`): `step(theta, opt_state, data)`
    -> (theta, opt_state, loss before the step), `init(theta)`, `value(theta, data)`."""
    optimizer = _optimizer(settings)

    def single(theta, opt_state, data):
        value_fn = lambda th: loss(th, data)  # noqa: E731
        if settings.optimizer == "lbfgs":
            value, grad = optax.value_and_grad_from_state(value_fn)(theta, state=opt_state)
            updates, opt_state = optimizer.update(grad, opt_state, theta, value=value, grad=grad, value_fn=value_fn)
        else:
            value, grad = jax.value_and_grad(value_fn)(theta)
            updates, opt_state = optimizer.update(grad, opt_state, theta)
        return optax.apply_updates(theta, updates), opt_state, value

    step = jax.jit(jax.vmap(single, in_axes=(0, 0, 0 if data_batched else None)))
    # strong dtypes: an optimizer state whose leaves start weakly typed (optax's line-search
    # info) comes back strongly typed from the first step, and the step would compile twice
    init = jax.jit(jax.vmap(lambda theta: jax.tree_util.tree_map(_strong, optimizer.init(theta))))
    value = jax.jit(jax.vmap(loss, in_axes=(0, 0 if data_batched else None)))
    return step, init, value
