"""Exact snapshots: every strategy's state comes back bit for bit; every corruption is named, never loaded."""

from __future__ import annotations

import io
import json
import zipfile
from dataclasses import replace

import numpy as np
import pytest
import scipy.sparse as sp

from linear_slam_ros.evaluation.synthetic import make_world, noisy_local_maps
from linear_slam_ros.joiner.joiner import Joiner, SavedJoiner, gate_step, global_result
from linear_slam_ros.joiner.registry import STRATEGIES
from linear_slam_ros.joiner.snapshot import (
    FORMAT_VERSION,
    SnapshotError,
    _checksum,
    decode_state,
    encode_state,
    read_snapshot,
    write_snapshot,
)
from linear_slam_ros.joining.gate import VarianceFactor


@pytest.fixture(scope="module")
def maps():
    world = make_world(2, 30, 30, np.random.default_rng(41))
    return noisy_local_maps(world, np.random.default_rng(42), steps_per_map=3, sensor_range=7.0)


def _same(a, b, path="value"):
    """Assert two state trees are identical: types, values, array bytes, dtypes and memory order."""
    assert type(a) is type(b), path
    if isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and a.shape == b.shape, path
        assert a.flags.f_contiguous == b.flags.f_contiguous and a.tobytes(order="A") == b.tobytes(order="A"), path
    elif sp.issparse(a):
        for attr in ("data", "indices", "indptr"):
            _same(getattr(a, attr), getattr(b, attr), f"{path}.{attr}")
        assert a.shape == b.shape, path
    elif isinstance(a, tuple):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _same(x, y, f"{path}[{i}]")
    elif hasattr(a, "__dataclass_fields__"):
        for name in a.__dataclass_fields__:
            if name != "layout":
                _same(getattr(a, name), getattr(b, name), f"{path}.{name}")
    else:
        assert a == b, path


@pytest.mark.parametrize("key", sorted(STRATEGIES, key=str))
def test_every_strategy_state_round_trips_bit_for_bit(key, maps, tmp_path):
    j = Joiner(*key)
    for seq, m in enumerate(maps[:7], start=1):
        j.offer(m, seq)
    j.offer(maps[8], 9)  # waits in the reorder buffer
    saved = j.save(journal_records=8)
    path = tmp_path / "state.npz"
    write_snapshot(path, saved)
    back = read_snapshot(path)
    _same(saved, back)
    assert not list(tmp_path.glob(".*.tmp"))  # the temporary file was renamed
    # and it carries on exactly: the restored joiner and the original join the next submaps alike
    other = Joiner(*key)
    other.restore(back)
    for joiner in (j, other):
        joiner.offer(maps[7], 8)
    ra, rb = global_result(j.state), global_result(other.state)
    assert ra.x.tobytes() == rb.x.tobytes()


def test_the_gate_variance_factor_round_trips_and_the_restored_gate_decides_alike(maps, tmp_path):
    j = Joiner("online-dc", gate_probability=0.99999999)
    for seq, m in enumerate(maps[:7], start=1):
        j.offer(m, seq)
    variance = j.state.variance
    assert variance.dof > 0 and variance.nis > 0 and variance.value != 1.0  # not the prior alone
    path = tmp_path / "gated.npz"
    write_snapshot(path, j.save())
    back = read_snapshot(path)
    assert back.state.variance == variance and back.state.variance.value == variance.value  # exact floats
    other = Joiner("online-dc", gate_probability=0.99999999)
    other.restore(back)
    ra, rb = (gate_step(x.state, maps[7], 0.99999999) for x in (j, other))
    assert (ra.nis, ra.threshold, ra.variance_factor) == (rb.nis, rb.threshold, rb.variance_factor)
    for joiner in (j, other):
        joiner.offer(maps[7], 8)
    assert j.state.variance == other.state.variance


def test_a_version_2_file_is_read_with_a_fresh_variance_factor(maps, tmp_path, caplog):
    j = Joiner("online-dc", gate_probability=0.99999999)
    for seq, m in enumerate(maps[:5], start=1):
        j.offer(m, seq)
    arrays = encode_state(j.save())
    header = json.loads(bytes(arrays["header"]).decode())
    del header["tree"]["fields"]["state"]["fields"]["variance"]  # what version 2 wrote
    header["version"] = 2
    body = {k: v for k, v in arrays.items() if k != "header"}
    header["sha256"] = _checksum(json.dumps(header["tree"], sort_keys=True, allow_nan=False).encode(), body)
    arrays["header"] = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
    old = tmp_path / "v2.npz"
    _rewrite(old, arrays)
    back = read_snapshot(old)
    assert back.state.variance == VarianceFactor() and "variance factor starts afresh" in caplog.text
    _same(replace(back.state, variance=j.state.variance), j.state)


def test_fortran_ordered_covariance_keeps_its_order(maps):
    j = Joiner("sequential")
    for seq, m in enumerate(maps[:3], start=1):
        j.offer(m, seq)
    cov = j.state.joined.global_map.cov_tilde
    assert cov.flags.f_contiguous and not cov.flags.c_contiguous
    back = decode_state(encode_state(j.save()))
    assert back.state.joined.global_map.cov_tilde.flags.f_contiguous


def _arrays(path):
    with np.load(path, allow_pickle=False) as npz:
        return {k: npz[k] for k in npz.files}


def _rewrite(path, arrays):
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    path.write_bytes(buf.getvalue())


def test_corruptions_are_named_and_never_loaded(maps, tmp_path):
    j = Joiner("online-dc")
    for seq, m in enumerate(maps[:5], start=1):
        j.offer(m, seq)
    good = tmp_path / "good.npz"
    write_snapshot(good, j.save())
    data = good.read_bytes()

    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(data[: len(data) // 2])
    with pytest.raises(SnapshotError, match=r"state file .*truncated.npz cannot be read \(truncated or not a state file"):
        read_snapshot(truncated)

    flipped = tmp_path / "flipped.npz"
    arrays = _arrays(good)
    key = next(k for k in arrays if k != "header" and arrays[k].dtype == np.float64 and arrays[k].size)
    arrays[key] = arrays[key].copy()
    arrays[key].flat[0] += 1e-12
    _rewrite(flipped, arrays)
    with pytest.raises(SnapshotError, match=r"flipped.npz: checksum mismatch \(the file is corrupt\)"):
        read_snapshot(flipped)

    other_version = tmp_path / "v99.npz"
    arrays = _arrays(good)
    header = json.loads(bytes(arrays["header"]).decode())
    header["version"] = FORMAT_VERSION + 98
    arrays["header"] = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
    _rewrite(other_version, arrays)
    expected = rf"v99.npz: format version {FORMAT_VERSION + 98}, this build reads version {FORMAT_VERSION}"
    with pytest.raises(SnapshotError, match=expected):
        read_snapshot(other_version)

    foreign = tmp_path / "foreign.npz"
    _rewrite(foreign, {"x": np.zeros(3)})
    with pytest.raises(SnapshotError, match="foreign.npz: no header"):
        read_snapshot(foreign)

    with pytest.raises(SnapshotError, match="missing.npz does not exist"):
        read_snapshot(tmp_path / "missing.npz")


def test_a_state_file_never_runs_code(tmp_path):
    pickled = tmp_path / "pickled.npz"
    with zipfile.ZipFile(pickled, "w") as zf:  # an object array needs pickle to load
        buf = io.BytesIO()
        np.save(buf, np.array([object()], dtype=object), allow_pickle=True)
        zf.writestr("header.npy", buf.getvalue())
    with pytest.raises(SnapshotError, match="cannot be read"):
        read_snapshot(pickled)
    arrays = encode_state(SavedJoiner(Joiner("sequential").state))
    header = json.loads(bytes(arrays["header"]).decode())
    header["tree"]["__type__"] = "Popen"
    arrays["header"] = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
    with pytest.raises(SnapshotError, match="checksum mismatch"):  # the checksum covers the tree
        decode_state(arrays)


def test_values_a_state_file_cannot_hold_are_refused():
    with pytest.raises(SnapshotError, match="cannot write a value of type set into a state file"):
        encode_state({1, 2})
    with pytest.raises(SnapshotError, match="cannot write a Joiner: not a class a state file may hold"):
        encode_state(Joiner("sequential"))
