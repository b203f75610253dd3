"""What a stage wrote into a folder that is not a run directory, and what each file was made from.

``mesh --out`` (or the ``mesh/`` folder beside another solver's frames) and ``view --headless
--out`` write into folders that also hold the user's own files. Such a folder gets a manifest, a
small JSON file naming every file the stage wrote there with a key for what it was made from (the
input's identity and the settings). From it:

- a file is skipped as done only when the manifest lists it with the key of this job, so a file of
  another input or other settings, or a user's file of the same name, is never taken for ours;
- a file the manifest does not list is never overwritten or removed: the stage refuses in one line;
- files are listed (with no key) before they are written, so an interrupted job leaves only files
  the next one knows to be its own.

Within a run directory, ``run.json`` plays this part (:mod:`whitecap.io.run`).
"""

from __future__ import annotations

import json
from pathlib import Path

from ..errors import InputError
from .atomic import write_text
from .run import check_relpath


class Manifest:
    """The manifest ``name`` in ``folder``: {relative path: key, or None while being written}."""

    def __init__(self, folder: str | Path, name: str):
        self.folder = Path(folder)
        self.path = self.folder / name
        self.files: dict[str, str | None] = {}
        self.simulation: str | None = None  # the run the files came from, where there is one (export)
        self.foreign = False  # a file of this name that is not whitecap's manifest
        try:
            data = json.loads(self.path.read_bytes().decode("utf-8"))
        except (OSError, ValueError):
            data = None  # none yet, or unreadable: nothing in the folder counts as ours
        if not isinstance(data, dict) or not (data.get("format") == FORMAT or isinstance(data.get("simulation"), str)):
            # Not whitecap's (an export.json of before this format names its simulation): it lists
            # nothing as ours, and it is the user's file, so it is not overwritten either.
            self.foreign = self.path.exists() or self.path.is_symlink()
            return
        self.simulation = data.get("simulation") if isinstance(data.get("simulation"), str) else None
        listed = data.get("files")
        entries = listed.items() if isinstance(listed, dict) else ((rel, None) for rel in listed or ())
        for rel, key in entries:
            try:
                check_relpath(rel, str(self.path))
            except InputError:
                continue  # never a path out of the folder
            self.files[rel] = key if isinstance(key, str) else None

    def current(self, rel: str, key: str) -> bool:
        """The file exists and was made from ``key``."""
        return self.files.get(rel) == key and (self.folder / rel).is_file()

    def refuse_foreign(self, rels, what: str) -> None:
        """A one-line error when one of ``rels`` (or the manifest's own name) exists but was not
        written here by whitecap."""
        if self.foreign:
            raise InputError(f"{self.path}: not a whitecap manifest; {what} keeps its list of written files under "
                             "this name: move the file, or choose another --out")
        for rel in rels:
            p = self.folder / rel
            if rel not in self.files and (p.exists() or p.is_symlink()):
                raise InputError(f"{p}: not written by whitecap (not in {self.path.name}); {what} would overwrite "
                                 "it: move it, or choose another --out")

    def plan(self, rels) -> None:
        """List ``rels`` before they are written (their key stays unknown until :meth:`record`)."""
        for rel in rels:
            self.files[check_relpath(rel, str(self.path))] = None
        self.save()

    def record(self, rel: str, key: str) -> None:
        self.files[rel] = key
        self.save()

    def keep_only(self, rels) -> None:
        """Remove every listed file not in ``rels`` (an earlier job's, an interrupted one's) and forget it."""
        keep = set(rels)
        for rel in [r for r in self.files if r not in keep]:
            (self.folder / rel).unlink(missing_ok=True)
            del self.files[rel]

    def save(self) -> None:
        data = {"format": FORMAT, **({"simulation": self.simulation} if self.simulation else {}), "files": self.files}
        write_text(self.path, json.dumps(data, indent=1, sort_keys=True) + "\n")


FORMAT = "whitecap-manifest"
