"""The repository revision a model was trained and exported at (manifest provenance)."""

from __future__ import annotations

import subprocess


def git_commit() -> str:
    """HEAD, marked dirty when the training package or its configurations differ from it."""
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", "training"], capture_output=True, text=True)
        return head + ("-dirty" if dirty.stdout.strip() else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
