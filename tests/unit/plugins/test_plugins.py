"""Plugin mechanism: libraries by entry point and by path; the implementation registry."""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from importlib import metadata
from pathlib import Path

import pytest

from btmission.diagnostics import Severity, SpecError
from btmission.plugins import (
    ENTRY_POINT_GROUP,
    Implementations,
    installed_libraries,
    load_library,
)
from btmission.spec.library import load_library_file


def test_builtin_libraries_are_registered_as_entry_points() -> None:
    eps = installed_libraries()
    assert {"aerial", "ground", "compra"} <= set(eps)
    assert eps["aerial"].value == "btmission_library.aerial:SPEC"
    assert eps["aerial"].group == ENTRY_POINT_GROUP


def test_load_by_name_and_by_path_agree() -> None:
    by_name = load_library("aerial")
    path = Path(str(by_name.library.file))
    by_path = load_library(str(path))
    assert by_name.origin.startswith("entry point") and by_path.origin.startswith("file")
    assert by_name.library.actions.keys() == by_path.library.actions.keys()
    assert by_name.implementations is not None  # module imported, registry found


def test_relative_path_resolves_against_base_dir(tmp_path: Path) -> None:
    (tmp_path / "lib.yaml").write_text(
        "library: mini\nversion: 1\nconditions: {a: ''}\nactions:\n  A: {post: [a]}\n"
    )
    assert load_library("lib.yaml", tmp_path).library.name == "mini"


def test_unknown_library_lists_installed_ones() -> None:
    with pytest.raises(SpecError) as exc:
        load_library("no_such_library")
    msg = exc.value.diagnostics[0].message
    assert "unknown library 'no_such_library'" in msg and "aerial" in msg


def test_unimportable_module_warns_but_library_still_synthesises(tmp_path: Path) -> None:
    f = tmp_path / "lib.yaml"
    f.write_text(
        "library: m\nversion: 1\nmodule: not_a_real_module_xyz\nconditions: {a: ''}\nactions:\n  A: {post: [a]}\n"
    )
    loaded = load_library(str(f))
    (d,) = [d for d in loaded.diagnostics if d.code == "module-import"]
    assert d.severity is Severity.WARNING and "cannot import implementation module" in d.message
    assert loaded.implementations is None and not loaded.runnable


def test_implementations_registry() -> None:
    impl = Implementations("t")

    @impl.action("go")
    class Go:
        pass

    @impl.condition("there")
    def there() -> bool:
        return True

    assert impl.actions == {"go": Go} and impl.conditions == {"there": there}
    with pytest.raises(ValueError, match="registered twice"):
        impl.action("go")(Go)
    lib, _ = load_library_file_text(
        "library: t\nversion: 1\nmodule: x\nconditions: {there: '', other: ''}\nactions:\n  go: {post: [there]}\n"
    )
    assert impl.missing(lib) == ["other"]
    assert impl.check(lib) == []
    impl.action("fly")(Go)
    (err,) = impl.check(lib)
    assert err.code == "unknown-implementation" and "'fly'" in err.message


def test_extend_starts_a_variant_with_everything_of_its_base() -> None:
    base = Implementations("base", vehicle="ground", settings={"speed_m_s": 0.4, "pick_s": 2.0})

    @base.action("go")
    class Go:
        pass

    @base.condition("there")
    def there() -> bool:
        return True

    @base.on_setup
    def home(ctx: object) -> None:
        pass

    variant = base.extend("variant", settings={"pick_s": 3.0, "extra": "x"})
    assert variant.library == "variant" and variant.vehicle == "ground"
    assert variant.settings == {"speed_m_s": 0.4, "pick_s": 3.0, "extra": "x"}
    assert variant.actions == {"go": Go} and variant.conditions == {"there": there}
    assert variant.setup_hooks == [home]
    variant.action("fly")(Go)
    variant.on_setup(there)
    assert "fly" not in base.actions and base.setup_hooks == [home]  # the base is untouched
    assert base.settings["pick_s"] == 2.0
    with pytest.raises(ValueError, match="'go' is registered twice"):
        variant.action("go")(Go)


def load_library_file_text(text: str):  # type: ignore[no-untyped-def]
    from btmission.spec.library import load_library_text

    return load_library_text(text, "t.yaml")


BUILT_IN_LIBRARIES = {"aerial", "aerial_mine", "compra", "ground", "haulage"}
PLUGIN = "thirdparty_demo"
PLUGIN_PACKAGE = "btmission_thirdparty_demo"


@pytest.fixture
def third_party_library(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[str]:
    """A third-party plugin installed as pip leaves one: a package beside its distribution's
    dist-info, whose entry_points.txt registers the library in btmission's group. The directory
    goes on sys.path for the test (importlib.metadata finds dist-info directories there)."""
    site = tmp_path / "site-packages"
    package = site / PLUGIN_PACKAGE
    package.mkdir(parents=True)
    (package / "__init__.py").write_text(
        'from pathlib import Path\n\nSPEC = Path(__file__).with_name("demo.yaml")\n'
    )
    (package / "demo.yaml").write_text(
        f"library: {PLUGIN}\nversion: 1\nconditions: {{parked: ''}}\n"
        "actions:\n  park: {post: [parked]}\n"
    )
    dist_info = site / "btmission_thirdparty_demo-0.1.dist-info"
    dist_info.mkdir()
    (dist_info / "METADATA").write_text(
        "Metadata-Version: 2.1\nName: btmission-thirdparty-demo\nVersion: 0.1\n"
    )
    (dist_info / "entry_points.txt").write_text(
        f"[{ENTRY_POINT_GROUP}]\n{PLUGIN} = {PLUGIN_PACKAGE}:SPEC\n"
    )
    monkeypatch.syspath_prepend(str(site))
    yield PLUGIN
    sys.modules.pop(PLUGIN_PACKAGE, None)


def test_entry_point_library_files_load_directly(third_party_library: str) -> None:
    """Every library of the entry-point group, the built-in ones and a third-party plugin's,
    designates a YAML file that loads on its own; btmission finds the plugin by name."""
    expected = {*BUILT_IN_LIBRARIES, third_party_library}
    seen: set[str] = set()
    for ep in metadata.entry_points(group=ENTRY_POINT_GROUP):
        if ep.name in expected:
            lib, diags = load_library_file(str(ep.load()))
            assert lib.name == ep.name and not diags
            seen.add(ep.name)
    assert seen == expected
    assert installed_libraries()[third_party_library].value == f"{PLUGIN_PACKAGE}:SPEC"
    loaded = load_library(third_party_library)
    assert loaded.origin == f"entry point {PLUGIN_PACKAGE}:SPEC"
    assert set(loaded.library.actions) == {"park"} and not loaded.diagnostics


def test_import_btmission_stays_light() -> None:
    """DESIGN/STYLE: the core must not pull heavy adapters (viewer, MAVLink, plotting, NMPC)."""
    code = (
        "import sys, btmission, btmission.synthesis.backchain, btmission.spec.mission\n"
        "heavy = {'meshcat', 'pymavlink', 'matplotlib', 'casadi', 'numba', 'ortools', 'click'}\n"
        "print(sorted(heavy & set(sys.modules)))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
