"""kpstudy.io: atomic writes leave no partial file and make files with the umask's mode;
the temporary files of a killed write are not carried into a finished dataset; code
fingerprints ignore documentation."""

from __future__ import annotations

import os
import stat

import pytest

from kpstudy.io import (
    source_fingerprint,
    staged_directory,
    tree_fingerprint,
    write_bytes_atomic,
    write_text_atomic,
)

CODE = '''"""Module docstring."""


def f(x):
    """Docstring."""
    # a comment
    return x + 1
'''


def test_tree_fingerprint_ignores_documentation_only(tmp_path):
    package = tmp_path / "pkg"
    package.mkdir()
    module = package / "m.py"
    module.write_text(CODE)
    before = tree_fingerprint(package)
    module.write_text(CODE.replace("Docstring.", "Other words.").replace("a comment", "note"))
    assert tree_fingerprint(package) == before
    module.write_text(CODE.replace('    """Docstring."""\n', ""))  # a function without one
    assert tree_fingerprint(package) == before
    module.write_text(CODE.replace("x + 1", "x + 2"))
    assert tree_fingerprint(package) != before
    module.write_text(CODE)
    (package / "n.py").write_text("y = 1\n")
    assert tree_fingerprint(package) != before


def test_source_fingerprint_is_stable_hex():
    first = source_fingerprint()
    assert first == source_fingerprint() and len(first) == 12
    int(first, 16)


def test_atomic_write_leaves_the_old_file_when_it_fails(tmp_path):
    target = tmp_path / "out" / "a.txt"
    write_text_atomic(target, "old")

    with pytest.raises(TypeError):  # fails inside the write, after the temporary file exists
        write_bytes_atomic(target, None)
    assert target.read_text() == "old"
    assert [p.name for p in target.parent.iterdir()] == ["a.txt"]


@pytest.fixture
def umask():
    """Set the process umask for the test (restored afterwards)."""
    previous = os.umask(0o022)
    yield lambda mask: os.umask(mask)
    os.umask(previous)


def mode(path) -> int:
    return stat.S_IMODE(os.stat(path).st_mode)


@pytest.mark.parametrize("mask", [0o022, 0o002, 0o077], ids=oct)
def test_atomic_writes_follow_the_umask(tmp_path, umask, mask):
    umask(mask)
    text = write_text_atomic(tmp_path / "a" / "t.txt", "x")
    data = write_bytes_atomic(tmp_path / "b.bin", b"x")
    plain = tmp_path / "plain.txt"
    plain.write_text("x")
    assert mode(text) == mode(data) == mode(plain) == 0o666 & ~mask
    assert not list(tmp_path.rglob(".*.tmp"))


def test_a_killed_writes_temporary_file_is_not_carried_into_the_dataset(
    tmp_path, umask, monkeypatch
):
    """An interrupted render leaves ``.<name>.<hex>.tmp`` files in the staging folder
    (the process was killed between creating and renaming them); the resumed run's
    finished dataset holds none of them."""
    from data_gen import dataset

    umask(0o022)
    out = tmp_path / "data"
    real = dataset._make
    calls = []

    def killed_after_one(job):
        if calls:
            raise KeyboardInterrupt  # the run stops here; what a kill left is added below
        calls.append(job)
        return real(job)

    monkeypatch.setattr(dataset, "_make", killed_after_one)
    with pytest.raises(KeyboardInterrupt):
        dataset.generate_dataset(out, 3, "160x100", seed=2, progress=False)
    monkeypatch.setattr(dataset, "_make", real)
    staging = tmp_path / ".data.partial"
    for stale in (staging / "images" / ".000001.png.0badc0de.tmp", staging / ".x.1234abcd.tmp"):
        stale.write_bytes(b"half a png")
    dataset.generate_dataset(out, 3, "160x100", seed=2, progress=False)
    assert not list(out.rglob("*.tmp"))
    assert sorted(p.name for p in (out / "images").iterdir()) == [f"{i:06d}.png" for i in range(3)]
    assert mode(out / "annotations.json") == mode(out / "images" / "000000.png") == 0o644


def test_staged_directory_drops_stale_temporary_files(tmp_path):
    out = tmp_path / "set"
    config = {"k": 1}
    with pytest.raises(KeyboardInterrupt):  # a run stopped in the middle of a write
        with staged_directory(out, config) as (staging, _):
            (staging / "sub").mkdir()
            (staging / "sub" / ".a.png.00000000.tmp").write_bytes(b"half")
            raise KeyboardInterrupt
    with staged_directory(out, config) as (staging, resumed):
        assert resumed
        write_text_atomic(staging / "sub" / "a.txt", "done")
    assert [p.relative_to(out).as_posix() for p in sorted(out.rglob("*"))] == [
        "sub",
        "sub/a.txt",
    ]
