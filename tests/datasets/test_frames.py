"""What the recordings' datasets share: the processed file's name from a digest of what it
depends on, and where the recording is read (VideoFrames and RosbagFrames test the rest)."""

import hashlib
from pathlib import Path
from types import SimpleNamespace

import pytest

from usf_graph.datasets.frames import LiftedFrames, digest


def test_the_digest_is_of_the_sorted_json_and_16_hex_digits():
    key = {"grid": "icosahedral:3", "every": 2, "camera": {"fx": 1.5, "model": "pinhole"}}
    flipped = {"camera": {"model": "pinhole", "fx": 1.5}, "every": 2, "grid": "icosahedral:3"}
    want = hashlib.sha256(b'{"camera": {"fx": 1.5, "model": "pinhole"}, "every": 2, '
                          b'"grid": "icosahedral:3"}').hexdigest()[:16]
    assert digest(key) == digest(flipped) == want  # the order of the keys does not matter
    assert digest({**key, "every": 3}) != want
    assert digest({"root": Path("/a/b")}) == digest({"root": "/a/b"})  # paths by their text


def test_a_recording_is_read_where_it_is_and_a_missing_one_is_named(tmp_path):
    frames = SimpleNamespace(source=tmp_path / "rec" / "walk.mp4")
    assert LiftedFrames.raw_dir.fget(frames) == str(tmp_path / "rec")
    assert LiftedFrames.raw_file_names.fget(frames) == ["walk.mp4"]
    with pytest.raises(FileNotFoundError, match=r"walk\.mp4 does not exist"):
        LiftedFrames.download(frames)
