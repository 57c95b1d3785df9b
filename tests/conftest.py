"""Shared fixtures. Correctness tests run in float64 (tests that need float32 cast explicitly)."""

import os

os.environ.setdefault("MPLBACKEND", "Agg")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import pytest  # noqa: E402

import jaxspring as js  # noqa: E402


@pytest.fixture(scope="session")
def scenes():
    """The four seed scenes, loaded once (float64)."""
    return {name: js.load_scene(name) for name in js.builtin_scenes()}
