"""One take reading path: the server's ``mocap.io.read_take`` and the client's ``facecast stream``
read C3D, TRC and CSV files through ``protocol.markers_file.read_take`` and agree."""

from __future__ import annotations

import numpy as np
import pytest

from facecast.client.commands import stream as stream_cmd
from facecast.protocol.markers_file import (
    TAKE_SUFFIXES,
    MarkerFileError,
    MarkerTake,
    read_take,
)
from facecast.server.drivers import SUFFIXES
from facecast.server.errors import InputError
from facecast.server.mocap import io


def _take(rng) -> MarkerTake:
    xyz = rng.normal(size=(20, 5, 3)) * 40.0 + [0.0, 100.0, 0.0]
    xyz[4, 2] = np.nan
    return MarkerTake(["CHIN", "LIP_L", "LIP_R", "HEAD1", "HEAD2"], xyz, 120.0, "mm")


def test_the_registry_and_the_reader_name_the_same_suffixes():
    assert set(TAKE_SUFFIXES) == {s for s, k in SUFFIXES.items() if k == "markers"}
    assert io.SUFFIXES == TAKE_SUFFIXES


@pytest.mark.parametrize("suffix", TAKE_SUFFIXES)
def test_server_and_client_read_the_same_take(tmp_path, rng, suffix):
    path = io.write_take(_take(rng), tmp_path / f"t{suffix.upper()}")  # suffixes in any case
    server = io.read_take(path)
    client = stream_cmd._read_markers(path)
    direct = read_take(path.read_bytes(), suffix, where=str(path))
    for t in (client, direct):
        assert t.names == server.names and t.fps == server.fps and t.units == server.units
        np.testing.assert_array_equal(t.xyz, server.xyz)


@pytest.mark.parametrize("suffix", TAKE_SUFFIXES)
def test_garbage_is_refused_the_same_way_by_both(tmp_path, suffix):
    path = tmp_path / f"bad{suffix}"
    path.write_bytes(b"\xff\xfe not a take \x00" * 7)
    with pytest.raises(MarkerFileError) as e:
        read_take(path.read_bytes(), suffix, where=str(path))
    with pytest.raises(InputError):
        io.read_take(path)
    with pytest.raises(stream_cmd.StreamError, match=str(path)):
        stream_cmd._read_markers(path)
    assert str(path) in str(e.value)


def test_an_unknown_suffix_is_a_file_error():
    with pytest.raises(MarkerFileError, match="unsupported take type '.bvh'; use one of .c3d"):
        read_take(b"", ".BVH", where="x.bvh")
