"""The code keeps the layering docs/architecture.md describes: every `crate::<module>` a module of
src/ names is one that the page's table says it may import, and no files of a module import each
other in a circle."""

from __future__ import annotations

import re
from pathlib import Path

from conftest import ROOT

ROW = re.compile(r"^\|\s*\d+\s*\|(?P<modules>[^|]+)\|[^|]*\|(?P<imports>[^|]+)\|\s*$")
NAME = re.compile(r"`([a-z_]+)(?:\.rs)?`")
CRATE_PATH = re.compile(r"\bcrate::([a-z_]+)")
SIBLING_PATH = re.compile(r"\bsuper::([a-z_]+)")


def allowed_imports(page: str) -> dict[str, set[str]]:
    """Module → the modules it may import, from the table's rows (`everything` for the command line)."""
    table: dict[str, set[str]] = {}
    for line in page.splitlines():
        row = ROW.match(line)
        if row is None:
            continue
        imports = set(NAME.findall(row["imports"]))
        for module in NAME.findall(row["modules"]):
            table[module] = imports
    return table


def strip_comments(source: str) -> str:
    """The code of a Rust file without its comments (a doc comment may name any module)."""
    return "\n".join(line.split("//", 1)[0] for line in source.splitlines())


def imports_of(module: str) -> dict[Path, set[str]]:
    """Each file of src/<module> (or src/<module>.rs) and the crate modules it names."""
    folder, single = ROOT / "src" / module, ROOT / "src" / f"{module}.rs"
    files = sorted(folder.rglob("*.rs")) if folder.is_dir() else [single]
    return {f: set(CRATE_PATH.findall(strip_comments(f.read_text()))) - {module} for f in files}


def test_every_module_imports_only_what_the_architecture_page_allows() -> None:
    table = allowed_imports((ROOT / "docs" / "architecture.md").read_text())
    assert {"mesh", "prior", "fem", "engine", "model", "data", "wire", "record", "client", "serve", "bench"} <= set(
        table
    ), f"the table lost a module: {sorted(table)}"
    crossings = [
        f"{path.relative_to(ROOT)} imports crate::{name}"
        for module, allowed in table.items()
        if (ROOT / "src" / module).is_dir() or (ROOT / "src" / f"{module}.rs").is_file()
        for path, names in imports_of(module).items()
        for name in sorted(names - allowed)
    ]
    assert not crossings, "imports the architecture page does not allow:\n" + "\n".join(crossings)


def circle(graph: dict[str, set[str]]) -> list[str]:
    """A cycle of `graph` (name → names it uses) as the names along it, or [] when there is none."""
    done: set[str] = set()

    def walk(node: str, path: list[str]) -> list[str]:
        if node in path:
            return path[path.index(node) :] + [node]
        if node in done:
            return []
        for next_node in sorted(graph.get(node, set())):
            found = walk(next_node, path + [node])
            if found:
                return found
        done.add(node)
        return []

    for start in sorted(graph):
        found = walk(start, [])
        if found:
            return found
    return []


def test_no_files_of_a_module_import_each_other_in_a_circle() -> None:
    circles = []
    for folder in sorted(p for p in (ROOT / "src").iterdir() if p.is_dir()):
        files = {f.stem: f for f in folder.glob("*.rs") if f.stem != "mod"}
        uses = {
            stem: set(SIBLING_PATH.findall(strip_comments(f.read_text()))) & (set(files) - {stem})
            for stem, f in files.items()
        }
        found = circle(uses)
        if found:
            circles.append(" -> ".join(f"{folder.name}/{stem}.rs" for stem in found))
    assert not circles, "files that import each other in a circle:\n" + "\n".join(circles)


def test_the_check_sees_a_forbidden_import() -> None:
    """The table parser and the scanner catch what they are for, on a made-up page and file."""
    page = "| 2 | `prior` | the Kelvinlet | `mesh` |\n| 7 | `serve`, `bench` | top | `prior`, `mesh` |\n"
    assert allowed_imports(page) == {"prior": {"mesh"}, "serve": {"prior", "mesh"}, "bench": {"prior", "mesh"}}
    code = "use crate::serve::Thing; // crate::engine is only named in a comment\nuse crate::mesh;\n"
    assert set(CRATE_PATH.findall(strip_comments(code))) - allowed_imports(page)["prior"] == {"serve"}
    assert circle({"shard": {"join"}, "join": {"dataset"}, "dataset": {"shard"}}) == [
        "dataset",
        "shard",
        "join",
        "dataset",
    ]
    assert circle({"join": {"dataset", "shard"}, "dataset": {"shard"}, "shard": set()}) == []
