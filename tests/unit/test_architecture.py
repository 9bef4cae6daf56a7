"""docs/architecture.md's floors, held against the code: every import of every module under service/,
drivers/ and plant_emulator/ (read with ast: imports inside functions and under TYPE_CHECKING count too)
must be one its floor may make ("What each floor may import"). FLOORS below is that table; the test also
reads the page, so a package cannot be added to the code, or a row to the page, without the other."""

from __future__ import annotations

import ast
import re
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PAGE = ROOT / "docs" / "architecture.md"
PACKAGES = ("service", "drivers", "plant_emulator")

# the wire contracts both sides of a wire import (drivers/__init__.py: the EDS files), and the process set-up
# both processes share; they import no other part of drivers/, so the emulator never drags the bus masters in.
# A name ending in ".__init__" is that package's own module only, not what lies under it.
DRIVER_CONTRACTS = (
    "drivers.__init__",
    "drivers.cia402",
    "drivers.daq_protocol",
    "drivers.lut_image",
    "drivers.blas_threads",
    "drivers.injection_limit",
)
# floor 0 of the service that every floor above it may import: the version, bench names, the error root, the
# words a validation item is said in
SERVICE_BASE = ("service", "service.names", "service.errors", "service.validation_words")
BELOW_API = (
    "service.calibration_service",
    "service.runs",
    "service.maps",
    "service.store",
    "service.bench",
    "service.identification",
    "service.model",
    "service.settings",
)
# what the API never imports: the machinery behind CalibrationService (the page: routes reach it only
# through the running service and the parts it holds; from below they take declarations and pure functions)
API_NEVER = (
    "service.runs.engine",
    "service.runs.sweep_run",
    "service.store.storage",
    "service.store.engines",
    "service.store.sqlite_engine",
    "service.store.postgres_engine",
    "service.bench.connections",
    "service.bench.lifecycle",
    "service.bench.run",
    "service.bench.measurement",
)


@dataclass(frozen=True)
class Floor:
    package: str  # as the page's table names it: `service/model/`, `service/settings.py`
    may_import: tuple[str, ...]  # module prefixes outside its own package
    never: tuple[str, ...] = ()  # prefixes refused even where may_import would let them through

    @property
    def module(self) -> str:
        """The package's dotted name: `service/model/` -> service.model, `service/__init__.py` -> service."""
        return self.package.removesuffix("/").removesuffix("/__init__.py").removesuffix(".py").replace("/", ".")

    def holds(self, module: str) -> bool:
        return module == "service" if self.module == "service" else _within(module, self.module)


FLOORS = (
    Floor("drivers/", ()),
    Floor("plant_emulator/", DRIVER_CONTRACTS),
    Floor("service/__init__.py", ()),
    Floor("service/names.py", ()),
    Floor("service/errors.py", ()),
    Floor("service/validation_words.py", ()),
    Floor("service/settings.py", ("service.names",)),
    Floor("service/model/", (*SERVICE_BASE, "service.settings")),
    Floor("service/identification/", (*SERVICE_BASE, "service.model", "drivers.injection_limit")),
    Floor(
        "service/store/",
        (
            *SERVICE_BASE,
            "service.identification",
            "service.model",
            "service.settings",
            "drivers.daq_protocol",
            "drivers.lut_image",
        ),
    ),
    Floor("service/bench/", (*SERVICE_BASE, "service.identification", "service.model", "service.settings", "drivers")),
    Floor(
        "service/maps/",
        (*SERVICE_BASE, "service.store", "service.identification", "service.model", "drivers.lut_image"),
    ),
    Floor(
        "service/runs/",
        (
            *SERVICE_BASE,
            "service.maps",
            "service.bench",
            "service.store",
            "service.identification",
            "service.model",
            "service.settings",
            "drivers.errors",
        ),
    ),
    Floor(
        "service/calibration_service.py",
        (
            *SERVICE_BASE,
            "service.runs",
            "service.maps",
            "service.bench",
            "service.store",
            "service.settings",
            "drivers",
        ),
    ),
    Floor("service/api/", (*SERVICE_BASE, *BELOW_API, "drivers.errors"), never=API_NEVER),
    Floor("service/paper/", (*SERVICE_BASE, *BELOW_API, "service.api", "drivers")),
    Floor("service/cli/", (*SERVICE_BASE, *BELOW_API, "service.api", "service.paper", "drivers")),
)


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _is_module(name: str) -> bool:
    base = ROOT.joinpath(*name.split("."))
    return base.with_suffix(".py").is_file() or (base / "__init__.py").is_file()


def _imports(path: Path) -> list[tuple[str, int]]:
    """(module imported, line) for every import of ours in the file; `from pkg import mod` names the module
    `pkg.mod`, `from pkg import name` names `pkg`."""
    module = _module_name(path)
    found = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            found += [(alias.name, node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: from the file's package, one level up per extra dot
                package = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
                base = ".".join(package[: len(package) - node.level + 1] + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            for alias in node.names:
                name = f"{base}.{alias.name}"
                found.append((name if _is_module(name) else base, node.lineno))
    return [(name, line) for name, line in found if name.split(".")[0] in PACKAGES]


def _within(name: str, prefix: str) -> bool:
    """name is the module `prefix` or lies under it (`x.__init__`: the package x's own module only)."""
    if prefix.endswith(".__init__"):
        return name == prefix.removesuffix(".__init__")
    return name == prefix or name.startswith(prefix + ".")


def _floor_of(module: str) -> Floor | None:
    """The most specific floor whose package holds the module."""
    holding = [f for f in FLOORS if f.holds(module)]
    return max(holding, key=lambda f: len(f.module)) if holding else None


def _sources() -> list[Path]:
    return sorted(p for package in PACKAGES for p in (ROOT / package).rglob("*.py"))


def test_every_module_has_a_floor_on_the_page():
    homeless = [str(p.relative_to(ROOT)) for p in _sources() if _floor_of(_module_name(p)) is None]
    assert not homeless, (
        f"no floor for {homeless}: give the package its row in docs/architecture.md's table "
        f"('What each floor may import') and in FLOORS of {Path(__file__).name}"
    )


def test_the_page_and_this_table_name_the_same_packages():
    rows = re.findall(r"^\|\s*\d+\s*\|\s*`([^`]+)`\s*\|", PAGE.read_text(encoding="utf-8"), flags=re.MULTILINE)
    assert sorted(rows) == sorted(f.package for f in FLOORS), (
        "docs/architecture.md's table and FLOORS here name different packages: "
        f"only on the page {sorted(set(rows) - {f.package for f in FLOORS})}, "
        f"only here {sorted({f.package for f in FLOORS} - set(rows))}"
    )


def test_every_import_is_one_its_floor_may_make():
    wrong = []
    for path in _sources():
        module = _module_name(path)
        floor = _floor_of(module)
        if floor is None:
            continue  # test_every_module_has_a_floor_on_the_page names it
        for name, line in _imports(path):
            if _floor_of(name) is floor:
                continue  # its own package
            allowed = any(_within(name, p) for p in floor.may_import) and not any(_within(name, p) for p in floor.never)
            if not allowed:
                wrong.append(f"{path.relative_to(ROOT)}:{line} imports {name} ({floor.package} may not)")
    assert not wrong, "imports against docs/architecture.md's floors:\n" + "\n".join(wrong)


def test_the_contracts_drag_no_master_in():
    """plant_emulator imports drivers/ contracts only; those import nothing else of drivers/."""
    wrong = [
        f"{path.relative_to(ROOT)}:{line} imports {name}"
        for path in _sources()
        if any(_within(_module_name(path), c) for c in DRIVER_CONTRACTS)
        for name, line in _imports(path)
        if not any(_within(name, c) for c in DRIVER_CONTRACTS)
    ]
    assert not wrong, "a wire contract imports a part of drivers/ that is not one:\n" + "\n".join(wrong)
