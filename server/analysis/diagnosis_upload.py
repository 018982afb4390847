"""A ROS 2 machine's rosbag2 recordings uploaded for a diagnosis (POST /api/diagnosis/uploads):
checked and stored on the request path, converted and diagnosed in a worker (server.analysis.diagnosis).

An upload is one or more bags, one per throw, each a single ``.mcap`` or ``.db3`` file or a
``.zip`` of a rosbag2 directory (``metadata.yaml`` and its storage files), plus the mapping file
(``.toml``, ``.json``, ``.yaml``: sim_twin.diagnosis.rosbag) and the impacts CSV (``throw_id,
target_x_m, target_y_m, impact_x_m, impact_y_m``). A throw's id is the file's or zip's stem. They
are kept under ``<data_dir>/uploads/<upload id>/`` (:func:`upload_dir`; the diagnosis job's spec
names the id): ``bags/<id>.mcap|.db3`` or ``bags/<id>/`` (the unzipped directory),
``mapping.<ext>``, ``impacts.csv``. Nothing here imports the twin (the API process
stays free of MuJoCo); what only conversion can tell (topics, joints, types) fails the run with
its reason.
"""

from __future__ import annotations

import csv
import io
import re
import shutil
import uuid
import zipfile
from pathlib import Path, PurePosixPath

from server.errors import Refused

MAX_UPLOAD_BYTES = 512 * 2**20
"""Default largest upload (all files, and all unzipped content), bytes (the server's setting
``max_bag_upload_bytes``)."""
MAX_BAGS = 500
BAG_SUFFIXES = (".mcap", ".db3", ".zip")
MAPPING_SUFFIXES = (".toml", ".json", ".yaml", ".yml")
_ID = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")


def new_upload_id() -> str:
    """A fresh upload id: 32 hex digits."""
    return uuid.uuid4().hex


def upload_dir(data_dir: Path, upload: str) -> Path:
    """``<data_dir>/uploads/<upload>/`` of an upload id (32 hex digits).

    Raises:
        ValueError: a malformed id (no path tricks).
    """
    if not re.fullmatch(r"[0-9a-f]{32}", upload or ""):
        raise ValueError(f"malformed upload id {upload!r}")
    return Path(data_dir) / "uploads" / upload


class UploadError(Refused, ValueError):
    """The upload cannot be used (the message says which file and why); nothing is kept."""


def _stem(name: str) -> tuple[str, str]:
    p = PurePosixPath(name.replace("\\", "/")).name
    stem, suffix = PurePosixPath(p).stem, PurePosixPath(p).suffix.lower()
    if not _ID.match(stem):
        raise UploadError(f"{name!r}: a file name (the throw id) must be 1-64 of A-Z a-z 0-9 _ . -")
    return stem, suffix


def _unzip(data: bytes, name: str, dest: Path, max_bytes: int) -> None:
    """Extract a zipped rosbag2 directory into ``dest`` (its files, flattened from the folder
    that holds metadata.yaml).

    Raises:
        UploadError: not a zip, no metadata.yaml, unsafe member paths, too large.
    """
    try:
        zf = zipfile.ZipFile(io.BytesIO(data))
    except zipfile.BadZipFile as e:
        raise UploadError(f"{name}: not a zip file ({e})") from e
    members = [m for m in zf.infolist() if not m.is_dir()]
    metas = [m for m in members if PurePosixPath(m.filename).name == "metadata.yaml"]
    if len(metas) != 1:
        raise UploadError(f"{name}: a zipped rosbag2 holds exactly one metadata.yaml, found {len(metas)}")
    root = PurePosixPath(metas[0].filename).parent
    if sum(m.file_size for m in members) > max_bytes:
        raise UploadError(f"{name}: unzips to more than {max_bytes} bytes")
    dest.mkdir(parents=True)
    for m in members:
        p = PurePosixPath(m.filename)
        if p.is_absolute() or ".." in p.parts or (m.external_attr >> 16) & 0o170000 == 0o120000:
            raise UploadError(f"{name}: unsafe member {m.filename!r}")
        if p.parent != root:
            continue  # only the bag's own folder
        if not _ID.match(p.name) and p.name != "metadata.yaml":
            raise UploadError(f"{name}: member {m.filename!r} has an unexpected name")
        with zf.open(m) as src, open(dest / p.name, "wb") as out:
            shutil.copyfileobj(src, out)


def _check_impacts(data: bytes, ids: list[str]) -> None:
    try:
        rows = list(csv.DictReader(io.StringIO(data.decode("utf-8"))))
    except UnicodeDecodeError as e:
        raise UploadError(f"impacts: not UTF-8 text ({e})") from e
    need = {"throw_id", "target_x_m", "target_y_m", "impact_x_m", "impact_y_m"}
    if not rows or not need <= set(rows[0]):
        raise UploadError(f"impacts: a CSV with columns {sorted(need)} and one row per throw")
    missing = sorted(set(ids) - {r["throw_id"] for r in rows})
    if missing:
        raise UploadError(f"impacts: no row for throws {missing}")


def store_upload(upload_dir: Path, bags: list[tuple[str, bytes]], mapping: tuple[str, bytes], impacts: bytes,
                 max_bytes: int | None = None) -> list[str]:
    """Check and write an upload under ``upload_dir`` (module doc); returns the throw ids.

    Raises:
        UploadError: no bags, too many or too large, a bad file name or suffix, two bags with one
            id, a bad zip, an impacts CSV without a row per throw. ``upload_dir`` is removed then.
    """
    if not bags:
        raise UploadError("no bags: upload one .mcap, .db3 or zipped rosbag2 per throw")
    if len(bags) > MAX_BAGS:
        raise UploadError(f"{len(bags)} bags: at most {MAX_BAGS}")
    max_bytes = max_bytes or MAX_UPLOAD_BYTES
    if sum(len(d) for _n, d in bags) + len(mapping[1]) + len(impacts) > max_bytes:
        raise UploadError(f"upload larger than {max_bytes} bytes")
    _m, msuffix = _stem(mapping[0])
    if msuffix not in MAPPING_SUFFIXES:
        raise UploadError(f"mapping {mapping[0]!r}: use a {'/'.join(MAPPING_SUFFIXES)} file")
    ids = []
    for name, _data in bags:
        stem, suffix = _stem(name)
        if suffix not in BAG_SUFFIXES:
            raise UploadError(f"{name!r}: a bag is a {'/'.join(BAG_SUFFIXES)} file")
        ids.append(stem)
    dupes = sorted({i for i in ids if ids.count(i) > 1})
    if dupes:
        raise UploadError(f"two bags for throws {dupes}")
    _check_impacts(impacts, ids)
    try:
        (upload_dir / "bags").mkdir(parents=True)
        for (name, data), tid in zip(bags, ids):
            suffix = _stem(name)[1]
            if suffix == ".zip":
                _unzip(data, name, upload_dir / "bags" / tid, max_bytes)
            else:
                (upload_dir / "bags" / f"{tid}{suffix}").write_bytes(data)
        (upload_dir / f"mapping{msuffix}").write_bytes(mapping[1])
        (upload_dir / "impacts.csv").write_bytes(impacts)
    except BaseException:
        shutil.rmtree(upload_dir, ignore_errors=True)
        raise
    return ids


def uploaded(upload_dir: Path) -> tuple[list[Path], Path, Path]:
    """(bag paths, mapping path, impacts path) of a stored upload."""
    bags = sorted((upload_dir / "bags").iterdir())
    mapping = next(p for p in upload_dir.iterdir() if p.name.startswith("mapping."))
    return bags, mapping, upload_dir / "impacts.csv"
