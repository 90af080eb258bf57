"""The plug-in registries (``magkf.plugins``): lazy loading, registration rules, entry points, and the layers
they keep straight."""

import ast
import importlib.util
import sys
from pathlib import Path

import pytest

from magkf.plugins import EFFECTS, FILTERS, MEASUREMENTS, READERS, REGISTRIES, PluginError, PluginWarning, Registry

ROOT = Path(__file__).resolve().parents[2]


def test_every_builtin_loads_and_subclasses_its_interface():
    interfaces = {
        "readers": "magkf.io.readers.LogReader",
        "filters": "magkf.online.filters.Filter",
        "measurements": "magkf.online.measurements.MeasurementModel",
        "effects": "magkf.effects.base.Effect",
    }
    for kind, registry in REGISTRIES.items():
        assert registry.interface.replace(":", ".") == interfaces[kind]
        for name in registry:
            cls = registry[name]
            assert cls.name == name
    assert list(READERS)[:7] == ["csv", "parquet", "ulog", "dataflash", "tlog", "rosbag", "mapped"]
    assert list(FILTERS)[:2] == ["ekf", "ukf"] and list(MEASUREMENTS)[:3] == ["magnitude", "vector", "both"]
    assert {"temperature_bias", "time_lag", "bias_drift"} <= set(EFFECTS)


def _fresh():
    """A registry of its own for a test, with one built-in filter."""
    return Registry("filter", "magkf.test_filters", "magkf.online.filters:Filter", {"ekf": "magkf.online.filters:EKF"})


def test_register_refuses_what_is_not_a_plugin_and_names_taken():
    from magkf.online.filters import EKF

    registry = _fresh()

    class NoName(EKF):
        name = ""

    class Builtin(EKF):
        name = "ekf"

    class Mine(EKF):
        name = "mine"

    class Other(EKF):
        name = "mine"

    with pytest.raises(PluginError, match="needs a name"):
        registry.register(NoName)
    with pytest.raises(PluginError, match="not a subclass"):
        registry.register(type("Stranger", (), {"name": "stranger"}))
    with pytest.raises(PluginError, match="magkf's own"):
        registry.register(Builtin)
    assert registry.register(Mine) is Mine and registry["mine"] is Mine
    with pytest.raises(PluginError, match="registered already"):
        registry.register(Other)
    registry.register(Other, replace=True)
    assert registry["mine"] is Other
    del registry["mine"]
    assert "mine" not in registry and list(registry) == ["ekf"]
    with pytest.raises(PluginError, match="stays"):
        registry.unregister("ekf")


def test_registering_the_class_a_name_stands_for_changes_nothing():
    from magkf.online.filters import EKF

    registry = _fresh()
    assert registry.register(EKF) is EKF and registry.origin("ekf") == "magkf"
    registry["ekf"]
    assert registry.register(EKF) is EKF and registry.origin("ekf") == "magkf"


def test_a_scope_undoes_what_was_registered_inside_it():
    from magkf.online.filters import EKF

    registry = _fresh()

    class Kept(EKF):
        name = "kept"

    class Passing(EKF):
        name = "passing"

    registry.register(Kept)
    with registry.restoring():
        registry.register(Passing)
        registry.unregister("kept")
        assert list(registry) == ["ekf", "passing"]
    assert list(registry) == ["ekf", "kept"] and registry["kept"] is Kept
    with pytest.raises(KeyError):
        registry["passing"]


def test_two_files_of_one_name_are_two_definitions(tmp_path):
    """An effect file is run as a module named after its stem: another file of that stem and class name is
    another definition, refused unless it replaces the first."""
    code = (
        "from magkf.effects import LinearEffect\n"
        "class Hull(LinearEffect):\n"
        "    name = 'hull'\n"
        "    parameter_names = ('h',)\n"
        "    def design(self, data):\n"
        "        import numpy as np\n"
        "        return np.zeros((len(data.time), 3, 1)) + {}\n"
    )
    classes = []
    for folder, value in (("a", 1.0), ("b", 2.0)):
        (tmp_path / folder).mkdir()
        path = tmp_path / folder / "hull.py"
        path.write_text(code.format(value))
        spec = importlib.util.spec_from_file_location("magkf_user_effect_hull", path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        classes.append(module.Hull)
    registry = Registry("effect", "magkf.test_effects", EFFECTS.interface, {})
    registry.register(classes[0])
    with pytest.raises(PluginError, match="registered already"):
        registry.register(classes[1])
    assert registry.register(classes[1], replace=True) is classes[1]


def test_a_plugin_that_fails_to_import_is_one_line_and_left_out_of_listings(tmp_path, monkeypatch):
    """Another package's plug-in whose module raises on import: a PluginError naming it when asked for, a
    PluginWarning and nothing else where every plug-in is gone through (format detection, candidates)."""
    (tmp_path / "boom_reader.py").write_text("raise RuntimeError('broken at import')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    registry = Registry("log reader", "magkf.test_readers", READERS.interface, {"csv": READERS.source("csv")})
    registry.register(READERS["csv"])
    registry._specs["boom"], registry._origins["boom"] = "boom_reader:Reader", "entry point"
    with pytest.raises(PluginError, match="'boom' cannot be loaded from 'boom_reader:Reader': RuntimeError: broken"):
        registry["boom"]
    with pytest.warns(PluginWarning, match="'boom' cannot be loaded"):
        assert [name for name, _ in registry.loadable()] == ["csv"]


def test_a_name_that_loads_nothing_says_where_it_looked():
    registry = Registry("filter", "magkf.test_filters", "magkf.online.filters:Filter", {"gone": "magkf.nowhere:Gone"})
    with pytest.raises(PluginError, match="'gone' cannot be loaded from 'magkf.nowhere:Gone'"):
        registry["gone"]
    with pytest.raises(KeyError):
        registry["never"]


def test_another_package_registers_through_an_entry_point(tmp_path, monkeypatch):
    """A package installed beside magkf: its distribution's entry_points.txt names the class, which loads
    only when asked for."""
    package = tmp_path / "hull_effects"
    package.mkdir()
    (package / "__init__.py").write_text(
        "import numpy as np\n"
        "from magkf.effects import LinearEffect\n\n"
        "class HullCurrent(LinearEffect):\n"
        "    name = 'hull_current'\n"
        "    parameter_names = ('h_x', 'h_y', 'h_z')\n"
        "    def design(self, data):\n"
        "        return np.zeros((len(data.time), 3, 3))\n"
    )
    info = tmp_path / "hull_effects-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: hull-effects\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text("[magkf.effects]\nhull_current = hull_effects:HullCurrent\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    registry = Registry("effect", "magkf.effects", EFFECTS.interface, {})
    with registry.restoring():  # read for the first time inside a scope, the entry point stays known after it
        assert "hull_current" in registry
    assert "hull_current" in registry and list(registry) == ["hull_current"]
    assert "hull_effects" not in sys.modules  # named, not yet imported
    assert registry["hull_current"].__name__ == "HullCurrent"
    assert registry.source("hull_current") == "hull_effects:HullCurrent"


def _imports(path: Path) -> set[str]:
    """The magkf modules a file imports, at any depth of the file (lazy imports inside functions too)."""
    package = ".".join(path.relative_to(ROOT).with_suffix("").parts[:-1])
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                module = ".".join(base + ([node.module] if node.module else []))
            elif node.module and node.module.startswith("magkf"):
                module = node.module
            else:
                continue
            out.add(module)
            out.update(f"{module}.{alias.name}" for alias in node.names)  # ``from .. import plausibility``
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names if a.name.startswith("magkf"))
    return out


#: Each layer and the layers it may import (lower ones). The foundation modules (magkf/*.py of one concept:
#: conventions, errors, status, plugins, config, calibration, files, timing, blas) import only each other.
LAYERS = {
    "foundation": set(),
    "reference": {"foundation"},
    "plausibility": {"foundation", "reference"},
    "io": {"foundation", "reference"},
    "effects": {"foundation"},
    "offline": {"foundation", "io", "reference", "plausibility"},
    "online": {"foundation", "io", "effects", "reference", "plausibility", "offline"},
    "sim": {"foundation", "io", "effects", "reference", "offline"},
    "apply": {"foundation", "io", "effects", "reference", "online"},
    "diagnostics": {"foundation", "io", "effects", "reference", "plausibility", "offline", "online", "apply"},
}
FOUNDATION = {
    "conventions",
    "errors",
    "status",
    "plugins",
    "config",
    "calibration",
    "families",
    "files",
    "timing",
    "blas",
}


def _layer(module: str) -> str | None:
    parts = module.split(".")
    if len(parts) < 2 or parts[0] != "magkf":
        return None
    if parts[1] in FOUNDATION:
        return "foundation"
    return parts[1] if parts[1] in LAYERS else None


@pytest.mark.parametrize("layer", sorted(LAYERS))
def test_no_import_runs_back_up_a_layer(layer):
    files = (
        [ROOT / "magkf" / f"{name}.py" for name in sorted(FOUNDATION)]
        if layer == "foundation"
        else [ROOT / "magkf" / f"{layer}.py"]
        if (ROOT / "magkf" / f"{layer}.py").exists()
        else sorted((ROOT / "magkf" / layer).rglob("*.py"))
    )
    allowed = LAYERS[layer] | {layer}
    upward = [
        f"{path.relative_to(ROOT)} imports {module}"
        for path in files
        for module in sorted(_imports(path))
        if _layer(module) is not None and _layer(module) not in allowed
    ]
    assert not upward, "\n".join(upward)
