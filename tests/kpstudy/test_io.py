"""kpstudy.io: atomic writes leave no partial file; code fingerprints ignore documentation."""

import pytest

from kpstudy.io import (
    source_fingerprint,
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
