"""Robot files: a robot TOML, a URDF arm, or a mounting TOML that bolts a URDF arm to a
satellite, read into a [`Robot`][spacegrasp_jax.core.model.Robot].

The readers sit one module above the model they build and the URDF reader they dispatch to:
[`spacegrasp_jax.core.model`][spacegrasp_jax.core.model] reads a robot TOML's tables
([`robot_from_tables()`][spacegrasp_jax.core.model.robot_from_tables]) and
[`spacegrasp_jax.core.urdf`][spacegrasp_jax.core.urdf] a URDF and a mounting; this module tells them apart.
"""

from __future__ import annotations

from pathlib import Path

from spacegrasp_jax.core import urdf
from spacegrasp_jax.core.inputs import parse_document, read_text
from spacegrasp_jax.core.model import Robot, RobotConfigError, robot_from_tables

#: How a URDF arm is mounted (``load_robot(..., mount=)``, ``--mount``): on the paper's
#: satellite, or as the URDF has it (its base link is the satellite body); else a file.
MOUNTS = ("paper", "urdf")


def load_robot(
    path: str | Path, *, mount: str | Path | None = None, base_link: str | None = None, tip_link: str | None = None
) -> Robot:
    """Read a robot from a TOML or URDF file.

    * A TOML robot (schema in the documentation's File formats and
      ``configs/paper_robot.toml``) has three tables, ``[satellite]``, ``[arm]`` and
      ``[end_effector]``, and an optional ``[limits]`` (``joint_rate`` in rad/s,
      ``joint_torque`` in N m, ``joint_position`` in rad); each key maps to one
      [`Robot`][spacegrasp_jax.core.model.Robot] field (``satellite.mass`` -> ``satellite_mass``,
      ``end_effector.offset`` -> ``ee_offset``, ``arm.link_com`` -> ``link_com``, ...). The arm
      is a DH table (``arm.dh_lambda``, ``arm.dh_length``, ``arm.dh_alpha``) or the chain's
      frames (``arm.frame_rotation``, ``arm.frame_position``).
    * A TOML with a ``[urdf]`` table mounts a URDF arm on a satellite
      ([`spacegrasp_jax.core.urdf.robot_from_mounting()`][spacegrasp_jax.core.urdf.robot_from_mounting]).
    * A ``.urdf`` file is an arm, the chain from ``base_link`` to ``tip_link`` (each ``None``:
      the URDF's one root link, its one leaf link). ``mount``: ``"paper"`` (the default) bolts
      its base link to the paper's 500 kg satellite at the paper's mount point; ``"urdf"``
      takes the URDF as the whole servicer, its base link the satellite body (the URDF that
      [`robot_to_urdf()`][spacegrasp_jax.core.urdf.robot_to_urdf] writes); a mounting file (a TOML
      with ``[satellite]`` and optional ``[limits]``, as a mounting TOML's) gives the satellite
      ([`spacegrasp_jax.core.urdf.urdf_arm()`][spacegrasp_jax.core.urdf.urdf_arm]).

    Raises:
        RobotConfigError: the file is not valid TOML or URDF, or a key or element is
            missing, unknown or invalid, or ``mount``, ``base_link`` or ``tip_link`` is given
            for a robot TOML; the message names the file and the key (``arm.link_mass``) or
            the element.
    """
    path = Path(path)
    return robot_from_text(
        read_text(path, RobotConfigError), source=str(path), mount=mount, base_link=base_link, tip_link=tip_link
    )


def rate_limits_stated(path: str | Path) -> bool:
    """Whether the robot file ``path`` (one [`load_robot()`][spacegrasp_jax.core.robot_files.load_robot]
    reads) states its joints' rate limits: a URDF does (``<limit velocity>`` is required), and
    so does a mounting TOML (its URDF's, or its own ``[limits]``); a robot TOML does when it
    gives ``limits.joint_rate``. Stated limits are the arm's own and success criteria; a
    7-joint TOML without them takes the paper's arm's assumed ``PAPER_JOINT_RATE_LIMIT``,
    which only detects runaways (the paper gives no rate limits).

    Raises:
        RobotConfigError: the file cannot be read or is not valid TOML.
    """
    path = Path(path)
    if path.suffix.lower() == ".urdf":
        return True
    document = parse_document(read_text(path, RobotConfigError), "toml", str(path), RobotConfigError)
    limits = document.get("limits")
    return "urdf" in document or (isinstance(limits, dict) and "joint_rate" in limits)


def robot_from_text(
    text: str,
    source: str,
    *,
    mount: str | Path | None = None,
    base_link: str | None = None,
    tip_link: str | None = None,
) -> Robot:
    """[`load_robot()`][spacegrasp_jax.core.robot_files.load_robot] on the text of the file ``source``
    (URDF if its name ends in ``.urdf``, else TOML)."""
    if Path(source).suffix.lower() == ".urdf":
        return urdf.urdf_arm(
            text, source, mount="paper" if mount is None else mount, base_link=base_link, tip_link=tip_link
        )
    given = [name for name, value in (("mount", mount), ("base_link", base_link), ("tip_link", tip_link)) if value]
    if given:
        raise RobotConfigError(
            f"{source}: {', '.join(given)}: for a URDF arm only (a robot TOML is the whole servicer; a mounting "
            f"TOML names its links in its [urdf] table and its satellite in [satellite])"
        )
    return robot_from_toml(text, source=source)


def robot_from_toml(text: str, source: str = "<robot TOML>") -> Robot:
    """[`load_robot()`][spacegrasp_jax.core.robot_files.load_robot] on the text of a TOML file; errors name
    ``source``, and a ``[urdf]`` table's file is found from ``source``'s folder."""
    document = parse_document(text, "toml", source, RobotConfigError)
    if "urdf" in document:
        return urdf.robot_from_mounting(document, source)
    return robot_from_tables(document, source)


__all__ = ["MOUNTS", "load_robot", "rate_limits_stated", "robot_from_text", "robot_from_toml"]
