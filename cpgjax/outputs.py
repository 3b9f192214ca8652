"""The catalogue of the files cpgjax writes. Each writing module declares its own files as :class:`OutputFile` entries
(its ``OUTPUTS``) and writes each file by its entry's name; the command line, the one layer that sees every writer,
gathers them (``cpgjax.show.catalogue``) for ``cpgjax show`` and docs/outputs.md, and tests/test_outputs.py checks
that the catalogue, docs/outputs.md and ``--overwrite`` (``cpgjax.study.files.claim_folder``) name the same files.

Here, below every writer: the entry type, the checks of the formats that entries share (JSON, parquet, rerun
recordings, PNG images, MP4 videos), the trial table, which the studies and the robot both write, and the metadata,
which the studies and ``walk`` write.
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
import re
from collections.abc import Callable

RRD_MAGIC = b"RRF2"  # the first bytes of a rerun recording file
RRD_FOOTER = b"RRF2FOOT"  # rerun's footer, 12 bytes before the end of a recording it finished writing


@dataclasses.dataclass(frozen=True)
class OutputFile:
    """One file, folder or family of files that a cpgjax command writes."""

    name: str  # its name as written; a family's as docs/outputs.md writes it (``best_<group>.mp4``, ``*.png``)
    meaning: str  # what it holds, as ``cpgjax show`` lists it
    # What is wrong with a non-empty written copy (truncated, corrupt), None if it reads back; a reader's exception
    # counts as corrupt.
    check: Callable[[pathlib.Path], str | None]
    pattern: str | None = None  # a family's regular expression, over whole file names; None: ``name`` itself

    def matches(self, name: str) -> bool:
        """Whether the file called ``name`` is this entry's."""
        return name == self.name if self.pattern is None else re.fullmatch(self.pattern, name) is not None


def entry_of(name: str, entries) -> OutputFile | None:
    """The entry of ``entries`` that the file called ``name`` is (a name before a family's pattern), None if none."""
    exact = [e for e in entries if e.pattern is None and e.matches(name)]
    return next(iter(exact or [e for e in entries if e.matches(name)]), None)


# ----------------------------------------------------------------------------------------------- format checks


def check_json(path: pathlib.Path) -> str | None:
    json.loads(path.read_text())
    return None


def check_parquet(path: pathlib.Path) -> str | None:
    import pyarrow.parquet as pq

    pq.read_metadata(path)
    return None


def check_recording(path: pathlib.Path) -> str | None:
    with open(path, "rb") as f:
        if f.read(len(RRD_MAGIC)) != RRD_MAGIC:
            return "not a rerun recording"
        f.seek(max(path.stat().st_size - 12, 0))
        if not f.read(12).startswith(RRD_FOOTER):
            return "truncated (no rerun footer: its writer stopped early; the viewer shows what it holds)"
    return None


def check_png(path: pathlib.Path) -> str | None:
    return None if path.read_bytes()[:4] == b"\x89PNG" else "not a PNG image"


def check_mp4(path: pathlib.Path) -> str | None:
    data = path.read_bytes()
    if data[4:8] != b"ftyp" or b"moov" not in data:  # an MP4's file-type box, and its index (written last)
        return "not a complete MP4 video (show --video films it again)"
    return None


def check_none(_path: pathlib.Path) -> str | None:
    """The check of a text table or a folder: none beyond its being there and, a file, not empty."""
    return None


TRIALS = "trials.parquet"
METADATA = "metadata.json"  # a study's, an optimization's and a walk's
OUTPUTS = (
    OutputFile(
        TRIALS, "one row per trial (and instance): conditions, parameters, J, velocity, CoT, falls", check_parquet
    ),
    OutputFile(METADATA, "how the run was made: command, version, commit, optimizer, machine, run figures", check_json),
)
