"""``python -m spacegrasp_jax.cli``: the ``spacegrasp`` command."""

from spacegrasp_jax.cli import run_command

if __name__ == "__main__":
    run_command()
