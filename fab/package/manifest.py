"""The file records of a fabrication package: each file's SHA-256 and size.

The manifest itself (``fab_manifest.json``) is written and read by
:mod:`doe.records.fab_manifest`.
"""

import hashlib
from pathlib import Path


def file_records(out_dir, names):
    """Return [{"path", "sha256", "bytes"}] for the named files of ``out_dir`` (sorted by path)."""
    out = []
    for name in sorted(names):
        data = (Path(out_dir) / name).read_bytes()
        out.append({"path": name, "sha256": hashlib.sha256(data).hexdigest(), "bytes": len(data)})
    return out
