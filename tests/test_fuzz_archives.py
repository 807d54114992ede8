"""A bounded sample of the fuzz campaign (scripts/fuzz_archives.py) on every run: mutated archives of every
kind end in a rejection naming the file or an unchanged result; never a traceback, a hang, an open outside the
tree or unbounded memory. strace must be installed (scripts/install.sh test installs it): the test fails, not
skips."""

from __future__ import annotations

import shutil

import numpy as np
from script_module import load_script


def load():
    return load_script("fuzz_archives")


def test_strace_is_there_to_see_every_file_the_batch_opens():
    assert shutil.which("strace"), "strace is needed to check that nothing outside the tree is opened"


def test_every_kind_of_mutated_archive_is_rejected_by_name_or_unchanged_and_nothing_breaks(tmp_path):
    fuzz = load()
    n = 2 * len(fuzz.KINDS)  # every kind at least twice, one `uwbcl process` run
    cases, outcome = fuzz.campaign(n, seed=20261123, batch=n, work=tmp_path)
    broken = {c.kind: outcome[c.index] for c in cases if outcome[c.index].startswith(fuzz.BROKEN)}
    assert broken == {}
    assert {c.kind for c in cases} == set(fuzz.KINDS)
    for c in cases:
        assert outcome[c.index].startswith(("rejected", "accepted")), (c, outcome)
    structural = [c for c in cases if c.kind in ("soft_loop", "external_link", "external_passwd", "virtual",
                                                 "external_storage", "huge_declared", "fifo", "empty",
                                                 "symlink_loop", "outside_symlink", "broken_symlink")]
    assert all(outcome[c.index].startswith("rejected") for c in structural), [
        (c.kind, c.detail, outcome[c.index])
        for c in structural if not outcome[c.index].startswith("rejected")]


def test_the_outside_open_check_sees_a_file_outside_the_allowed_trees(tmp_path):
    fuzz = load()
    log = tmp_path / "strace.log"
    log.write_text('123 openat(AT_FDCWD, "/etc/passwd", O_RDONLY) = 3\n'
                   f'123 openat(AT_FDCWD, "{tmp_path}/tree/a.h5", O_RDONLY) = 4\n'
                   f'123 openat(AT_FDCWD, "{tmp_path}/treehouse.h5", O_RDONLY) = 5\n'
                   f'123 openat(AT_FDCWD, "{tmp_path}", O_RDONLY|O_DIRECTORY) = 6\n')
    assert fuzz.opened_outside(log, [tmp_path / "tree"]) == ["/etc/passwd", f"{tmp_path}/treehouse.h5"]
    assert np.isfinite(fuzz.RSS_LIMIT_KB)
