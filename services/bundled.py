"""Where tether's own data files are: the worlds by name and the default safety policy. Nothing heavy loaded.

The recorder keeps a copy of the world and policy files safety runs with and needs only their paths;
reading them (services/worldmodel.py, services/safety/policyfile.py) takes shapely and numpy.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

DEFAULT_WORLD = "household"
DEFAULT_POLICY = Path(__file__).with_name("safety") / "policy.toml"


def world_path(name_or_path: str | Path = DEFAULT_WORLD) -> Path:
    """A bundled world by name ('household'), or a path to a world file."""
    path = Path(name_or_path)
    if path.suffix in (".yaml", ".yml", ".json") or path.exists():
        return path
    bundled = resources.files("services") / "worlds" / f"{name_or_path}.yaml"
    return Path(str(bundled))
