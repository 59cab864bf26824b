"""The type stubs (gelstereo.pyi) describe the module as built: every function, class and member
they declare exists, and the wheel ships them."""

import ast
from pathlib import Path

import gelstereo

STUBS = Path(__file__).resolve().parents[1] / "gelstereo.pyi"
TYPING_ONLY = {"Image", "SlipState", "Markers"}  # aliases and TypedDicts for annotations only


def test_every_stubbed_name_exists():
    tree = ast.parse(STUBS.read_text())
    declared = 0
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.ClassDef)) and node.name not in TYPING_ONLY:
            assert hasattr(gelstereo, node.name), node.name
            declared += 1
        if isinstance(node, ast.ClassDef) and node.name not in TYPING_ONLY:
            for member in node.body:
                name = getattr(member, "name", None) or getattr(getattr(member, "target", None), "id", None)
                if name and not name.startswith("__"):
                    assert hasattr(getattr(gelstereo, node.name), name), f"{node.name}.{name}"
    assert declared >= 5


def test_the_installed_package_carries_the_stubs():
    package = Path(gelstereo.__file__).parent
    assert (package / "py.typed").exists()
    assert (package / "__init__.pyi").read_text() == STUBS.read_text()
