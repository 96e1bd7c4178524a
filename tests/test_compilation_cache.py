"""The persistent compilation cache holds machine code this process runs: its folder must be
the user's alone, and an entry that is damaged or was not written through gst_jax is compiled
afresh, never loaded (issue 94)."""

from __future__ import annotations

import os
import stat
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from gst_jax import cli, compiles
from gst_jax.errors import DataError
from gst_jax.private_folders import private_folder


def test_a_new_cache_folder_is_made_for_its_user_alone(tmp_path):
    folder = private_folder(tmp_path / "new" / "xla")
    assert folder.is_dir() and stat.S_IMODE(folder.stat().st_mode) == 0o700


@pytest.mark.parametrize("mode", [0o777, 0o1777, 0o775])
def test_a_folder_others_may_write_is_refused(tmp_path, mode):
    """A world-writable folder (sticky or not, as a shared /tmp/cache would be) and a
    group-writable one: whoever writes there could plant code."""
    folder = tmp_path / "shared"
    folder.mkdir()
    folder.chmod(mode)
    with pytest.raises(DataError, match="writable by others.*chmod go-w"):
        private_folder(folder)


def test_a_folder_inside_one_others_may_write_is_refused(tmp_path):
    (tmp_path / "open").mkdir()
    (tmp_path / "open").chmod(0o777)                  # no sticky bit: others may rename
    (tmp_path / "open" / "xla").mkdir(mode=0o700)
    with pytest.raises(DataError, match="lies in .*open, which others may write"):
        private_folder(tmp_path / "open" / "xla")
    (tmp_path / "open").chmod(0o1777)                 # sticky, as /tmp: ours stays ours
    assert private_folder(tmp_path / "open" / "xla") == tmp_path / "open" / "xla"


def test_a_folder_of_another_user_is_refused(tmp_path, monkeypatch):
    folder = tmp_path / "theirs"
    folder.mkdir(mode=0o700)
    monkeypatch.setattr(os, "geteuid", lambda: folder.stat().st_uid + 1)
    with pytest.raises(DataError, match="belongs to another user"):
        private_folder(folder)


def test_a_file_a_link_or_nothing_is_refused(tmp_path):
    (tmp_path / "file").write_text("")
    (tmp_path / "mine").mkdir(mode=0o700)
    (tmp_path / "link").symlink_to(tmp_path / "mine")
    with pytest.raises(DataError, match="not a folder"):
        private_folder(tmp_path / "file")
    with pytest.raises(DataError, match="symbolic link"):
        private_folder(tmp_path / "link")
    with pytest.raises(DataError, match="folder is empty"):
        private_folder("")


def test_the_commands_refuse_a_shared_cache_folder_in_one_line(tmp_path, capsys):
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o1777)
    parser = cli.parser("test", "A command that compiles one program.")
    cli.add_compilation_cache_flag(parser)
    for folder in (str(shared), ""):
        with pytest.raises(SystemExit) as stop:
            cli.run(lambda args: pytest.fail("ran"), parser, ["--compilation-cache", folder])
        assert str(stop.value).startswith("error: the compilation cache folder")
        assert "\n" not in str(stop.value)


def _entries(folder, name):
    return sorted(p for p in folder.iterdir() if p.name.endswith("-cache") and name in p.name)


def test_a_damaged_or_foreign_entry_is_compiled_afresh_and_replaced(tmp_path,
                                                                    own_compilation_cache):
    """An entry with a byte changed (a damaged disk, a half-written file) and an entry jax
    wrote without gst_jax (another program's, an older version's) are not loaded: the program
    is compiled again, with one warning, and the entry replaced by a checked one."""
    folder = tmp_path / "xla"
    compiles.use_persistent_cache(folder)
    def program(x):
        return jnp.sin(x) * 3.0 + 1.0

    x = np.arange(5.0, dtype=np.float32)
    expected = np.asarray(jax.jit(program)(x))
    (entry,) = _entries(folder, "program")
    good = entry.read_bytes()
    assert good.startswith(compiles.ENTRY_HEADER)

    for bad in (good[:-40] + bytes(40), good[len(compiles.ENTRY_HEADER) + 32:]):
        entry.write_bytes(bad)
        jax.clear_caches()
        compiles.jax_cache.reset_cache()              # a new process: a new warning
        with pytest.warns(UserWarning, match="damaged or was not written by gst_jax"):
            np.testing.assert_array_equal(jax.jit(program)(x), expected)
        assert entry.read_bytes().startswith(compiles.ENTRY_HEADER) and entry.read_bytes() != bad

    jax.clear_caches()                                # the replaced entry loads quietly
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        np.testing.assert_array_equal(jax.jit(program)(x), expected)
