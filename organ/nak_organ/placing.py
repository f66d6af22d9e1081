"""Placing the written files: nak's own loader checks them first, so that DIR holds only a mesh nak takes.

organ.msh and model.toml are written into a staging folder inside DIR, and `nak mesh info` loads them there
(every check `nak serve --mesh` makes: volumes, topology, node sets on the surface and apart, the
configuration). Accepted, they replace DIR's files; refused, the staging folder becomes DIR/refused-by-nak,
DIR's files are left as they were, and nak's reason is the refusal, naming the refused file, what is
wrong and where (nak names an element, a node or a key). Without a nak binary the files are placed
unchecked, and the summary says so.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
from pathlib import Path

from .errors import OrganInputError

ROOT = Path(__file__).resolve().parents[2]
MSH_NAME = "organ.msh"
FILES = (MSH_NAME, "model.toml")
REFUSED = "refused-by-nak"


def default_nak() -> Path:
    """$NAK_BIN, else the repository's release build."""
    named = os.environ.get("NAK_BIN")
    return Path(named) if named else ROOT / "target" / "release" / "nak"


def staging_folder(out: Path) -> Path:
    """An empty folder inside `out` (created) for the files before they are checked."""
    try:
        out.mkdir(parents=True, exist_ok=True)
        return Path(tempfile.mkdtemp(prefix=".staging-", dir=out))
    except OSError as e:
        raise OrganInputError([f"--out {out}: cannot write there: {e.strerror}"]) from None


def place(staging: Path, out: Path, nak: Path) -> str:
    """Moves the staged files into `out` once `nak mesh info` accepts them (or when there is no `nak` to
    ask); returns what was checked, for the summary. Raises OrganInputError when nak refuses them."""
    if not nak.is_file():
        _move(staging, out)
        return (
            f"not by nak mesh info: no nak binary at {nak} (build it with `cargo build --release` or give "
            "--nak PATH), so `nak mesh info DIR` has not seen these files"
        )
    environment = {**os.environ, "RUST_BACKTRACE": "0", "RUST_LIB_BACKTRACE": "0"}
    result = subprocess.run(
        [str(nak), "mesh", "info", str(staging)], capture_output=True, text=True, env=environment, check=False
    )
    if result.returncode == 0:
        _move(staging, out)
        shutil.rmtree(out / REFUSED, ignore_errors=True)
        return f"nak mesh info accepts the mesh and its configuration ({nak})"
    refused = out / REFUSED
    shutil.rmtree(refused, ignore_errors=True)
    staging.rename(refused)
    reason = nak_reason(result.stderr).replace(str(staging), str(refused))
    raise OrganInputError([f"nak mesh info refuses the written mesh ({out} is unchanged; see {refused}): {reason}"])


def nak_reason(stderr: str) -> str:
    """The innermost cause in a failed nak command's error report (anyhow's "Error: …", then "Caused by:"
    and its causes, numbered "0: …", "1: …" when there are several): the mesh loader's own message, which
    names the file and where. The report's first line when it has no causes."""
    lines = [line.strip() for line in stderr.splitlines()]
    lines = lines[: lines.index("Stack backtrace:")] if "Stack backtrace:" in lines else lines
    causes = [line for line in lines[lines.index("Caused by:") + 1 :] if line] if "Caused by:" in lines else []
    if causes:
        number, colon, rest = causes[-1].partition(": ")
        return rest if colon and number.isdigit() else causes[-1]
    first = next((line for line in lines if line), "exited with an error and no message")
    return first.removeprefix("Error: ")


def _move(staging: Path, out: Path) -> None:
    for name in FILES:
        os.replace(staging / name, out / name)
    staging.rmdir()
