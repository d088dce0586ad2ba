"""The bundled geometry and demo capture (package data) are the repository's folders, copied."""

from __future__ import annotations

from pathlib import Path

from fitmedia.data import bundled_path

ROOT = Path(__file__).resolve().parents[1]
COPIED = [("capture_specs", "*.yaml"), ("synthetic/default", "*.yaml"),
          ("synthetic/default", "*.json"), ("synthetic/default/images", "*.tiff")]


def test_package_copies_are_identical_to_the_repository_folders():
    """Byte for byte, both ways (a file added or removed on one side fails too); the repository's
    capture_specs/ and synthetic/default/ are the source of truth: `make package-data` copies."""
    seen = 0
    for folder, pattern in COPIED:
        repo = {p.name: p.read_bytes() for p in (ROOT / folder).glob(pattern)}
        pkg = {p.name: p.read_bytes() for p in bundled_path(*folder.split("/")).glob(pattern)}
        assert sorted(pkg) == sorted(repo), (folder, pattern, "run `make package-data`")
        for name in repo:
            assert pkg[name] == repo[name], f"{folder}/{name} differs: run `make package-data`"
        seen += len(repo)
    assert seen >= 8


def test_demo_and_validate_defaults_are_bundled():
    """`fitmedia demo` and `validate`'s default geometry read the package's copies."""
    from fitmedia.batch import DEFAULT_GEOMETRY
    from fitmedia.spec import load_spec

    assert DEFAULT_GEOMETRY == bundled_path("capture_specs", "bulb.yaml")
    assert DEFAULT_GEOMETRY.is_file()
    spec = load_spec(bundled_path("synthetic", "default", "capture.yaml"))
    assert all(p.is_file() for e in spec.images for p in e.paths)
