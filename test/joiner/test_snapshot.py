"""Exact snapshots: every strategy's state comes back bit for bit; every corruption is named, never loaded."""

from __future__ import annotations

import contextlib
import gc
import hashlib
import io
import json
import os
import threading
import zipfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse as sp

from linear_slam_ros.evaluation.synthetic import make_world, noisy_local_maps
from linear_slam_ros.joiner.joiner import Joiner, SavedJoiner, gate_step, global_result
from linear_slam_ros.joiner.registry import STRATEGIES
from linear_slam_ros.joiner.snapshot import (
    FORMAT_VERSION,
    BlobStore,
    SnapshotError,
    _checksum,
    blob_names,
    decode_state,
    encode_state,
    read_snapshot,
    write_snapshot,
)
from linear_slam_ros.joining.divide_conquer import Deferred
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
        lower = getattr(type(a), "LOWER_TRIANGLE_FIELDS", ())  # only their lower triangle is the value
        for name in a.__dataclass_fields__:
            x, y = getattr(a, name), getattr(b, name)
            if name in lower:
                x, y = np.asfortranarray(np.tril(x)), np.asfortranarray(np.tril(y))
            if name not in ("layout", "LOWER_TRIANGLE_FIELDS"):
                _same(x, y, f"{path}.{name}")
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


def _rewritten(j, edit, version):
    """The arrays of ``j``'s state file with its ``JoinerState`` fields edited by ``edit``, re-hashed as ``version``."""
    arrays = encode_state(j.save())
    header = json.loads(bytes(arrays["header"]).decode())
    edit(header["tree"]["fields"]["state"]["fields"])
    header["version"] = version
    body = {k: v for k, v in arrays.items() if k != "header"}
    header["sha256"] = _checksum(json.dumps(header["tree"], sort_keys=True, allow_nan=False).encode(), body)
    arrays["header"] = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
    return arrays


def _gated_joiner(maps):
    j = Joiner("online-dc", gate_probability=0.99999999)
    for seq, m in enumerate(maps[:5], start=1):
        j.offer(m, seq)
    return j


def test_a_version_2_file_is_read_with_a_fresh_variance_factor(maps, tmp_path, caplog):
    j = _gated_joiner(maps)
    old = tmp_path / "v2.npz"
    _rewrite(old, _rewritten(j, lambda fields: fields.pop("variance"), 2))  # what version 2 wrote
    back = read_snapshot(old)
    assert back.state.variance == VarianceFactor() and "variance factor starts afresh" in caplog.text
    _same(replace(back.state, variance=j.state.variance), j.state)


@pytest.mark.parametrize("version", [3, 4])
def test_a_version_3_or_4_variance_factor_drops_its_prior_submaps(maps, tmp_path, caplog, version):
    j = _gated_joiner(maps)

    def as_before_5(fields):  # what versions 3 and 4 wrote
        variance = fields["variance"]["fields"]
        del variance["tail_confidence"]
        variance["prior_submaps"] = 20

    old = tmp_path / f"v{version}.npz"
    _rewrite(old, _rewritten(j, as_before_5, version))
    back = read_snapshot(old)
    assert back.state.variance == j.state.variance and len(back.state.variance.tail) > 0
    assert "prior_submaps is not used" in caplog.text


def test_a_current_file_naming_prior_submaps_or_a_bad_tail_is_refused(maps):
    j = _gated_joiner(maps)
    arrays = _rewritten(j, lambda fields: fields["variance"]["fields"].update(prior_submaps=20), FORMAT_VERSION)
    with pytest.raises(SnapshotError, match="malformed state .*unexpected keyword argument 'prior_submaps'"):
        decode_state(arrays)

    def negative_tail(fields):  # NaN and infinity cannot pass the header's JSON; a negative u can
        fields["variance"]["fields"]["tail"]["__tuple__"][0] = -1.0

    with pytest.raises(SnapshotError, match=r"malformed state .*VarianceFactor.tail\[0\]=-1.0 must be a finite number"):
        decode_state(_rewritten(j, negative_tail, FORMAT_VERSION))


def test_fortran_ordered_covariance_keeps_its_order(maps):
    j = Joiner("sequential")
    for seq, m in enumerate(maps[:3], start=1):
        j.offer(m, seq)
    cov = j.state.joined.global_map.cov_tilde
    assert cov.flags.f_contiguous and not cov.flags.c_contiguous
    back = decode_state(encode_state(j.save()))
    assert back.state.joined.global_map.cov_tilde.flags.f_contiguous


def test_the_unused_upper_triangle_of_the_covariance_is_written_as_zeros(maps):
    """The sequential map keeps S~ in its lower triangle; the upper one holds whatever the memory
    held (two identical runs differed there, in heap bytes written to the file)."""
    j = Joiner("sequential")
    for seq, m in enumerate(maps[:3], start=1):
        j.offer(m, seq)
    g = j.state.joined.global_map
    upper = np.triu_indices(g.cov_tilde.shape[0], 1)
    junk = np.asfortranarray(g.cov_tilde.copy())
    junk[upper] = np.nan
    joined = replace(j.state.joined, global_map=replace(g, cov_tilde=junk))
    state = replace(j.state, chains=(replace(j.state.chains[0], joined=joined),))
    written = decode_state(encode_state(state)).joined.global_map.cov_tilde
    assert written.flags.f_contiguous and np.all(written[upper] == 0.0)
    np.testing.assert_array_equal(np.tril(written), np.tril(g.cov_tilde))
    assert np.isnan(junk[upper]).all()  # the state in memory is left as it is


def _arrays(path):
    with np.load(path, allow_pickle=False) as npz:
        return {k: npz[k] for k in npz.files}


def _arrays_of(data):
    with np.load(io.BytesIO(data), allow_pickle=False) as npz:
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


def test_only_a_regular_file_is_read_as_a_state(tmp_path):
    """A FIFO would block the node's executor until a writer closed it, /dev/zero would fill its memory."""
    fifo = tmp_path / "fifo.npz"
    os.mkfifo(fifo)
    with pytest.raises(SnapshotError, match=r"state file .*fifo.npz is not a regular file"):
        read_snapshot(fifo)
    with pytest.raises(SnapshotError, match=r"state file /dev/zero is not a regular file"):
        read_snapshot(Path("/dev/zero"))
    with pytest.raises(SnapshotError, match=r"state file .* is not a regular file"):
        read_snapshot(tmp_path)


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


def _online_dc(maps, n, **options):
    """An online-D&C joiner that has joined ``maps[:n]``."""
    j = Joiner("online-dc", **options)
    for seq, m in enumerate(maps[:n], start=1):
        j.offer(m, seq)
    return j


def _deferred_joiner(maps, n):
    """An online-D&C joiner whose every merge is deferred and, with no worker, left to compute."""
    return _online_dc(maps, n, defer_above=0)


def test_a_merge_not_computed_yet_is_written_as_its_inputs_without_computing_or_waiting(maps, tmp_path):
    j = _deferred_joiner(maps, 6)
    pending = [e for e in j.state.joined.stack if isinstance(e, Deferred)]
    assert pending and not any(e.done for e in pending)
    held = pending[0]._lock  # a worker busy with the merge holds it: writing must not wait for it
    with held:
        writer = threading.Thread(target=write_snapshot, args=(tmp_path / "state.npz", j.save()))
        writer.start()
        writer.join(timeout=30.0)
        assert not writer.is_alive()
    assert not any(e.done for e in pending)  # nothing was computed by writing
    restored = read_snapshot(tmp_path / "state.npz")
    again = [e for e in restored.state.joined.stack if isinstance(e, Deferred)]
    assert len(again) == len(pending) and not any(e.done for e in again)
    assert [e.count for e in again] == [e.count for e in pending]
    _same(global_result(restored.state), global_result(j.state))  # the same merges, bit for bit


def test_large_maps_are_written_once_as_blobs_named_by_checksum(maps, tmp_path):
    j = _online_dc(maps, 8)
    blobs = BlobStore(tmp_path / "blobs", min_bytes=0)
    write_snapshot(tmp_path / "a.npz", j.save(), blobs)
    first = sorted(p.name for p in blobs.folder.iterdir())
    names = blob_names(tmp_path / "a.npz")
    assert first == sorted(f"{n}.npz" for n in names) and len(names) == len(j.state.joined.stack)
    mtimes = {p.name: p.stat().st_mtime_ns for p in blobs.folder.iterdir()}
    j.offer(maps[8], 9)  # the 8-submap level stays; a new 1-submap level comes
    write_snapshot(tmp_path / "b.npz", j.save(), blobs)
    after = {p.name: p.stat().st_mtime_ns for p in blobs.folder.iterdir()}
    assert len(after) == len(mtimes) + 1 and all(after[n] == t for n, t in mtimes.items())  # none rewritten
    _same(read_snapshot(tmp_path / "b.npz"), read_snapshot(tmp_path / "b.npz", blobs))  # found beside the file
    _same(read_snapshot(tmp_path / "b.npz").state, j.save().state)
    write_snapshot(tmp_path / "whole.npz", j.save())  # without a store, the file holds everything
    assert blob_names(tmp_path / "whole.npz") == set()
    _same(read_snapshot(tmp_path / "whole.npz").state, j.save().state)
    assert blobs.collect(blob_names(tmp_path / "b.npz")) == 0  # b names every blob: a's levels are b's
    del j
    gc.collect()
    blobs.sync()  # forgets the maps that are gone: the joined 8-submap level; submap 9 lives on in maps
    assert [ref() for ref, _ in blobs._written.values()] == [maps[8]]


def test_blob_corruptions_are_named_and_never_loaded(maps, tmp_path):
    j = _online_dc(maps, 4)
    blobs = BlobStore(tmp_path / "blobs", min_bytes=0)
    write_snapshot(tmp_path / "state.npz", j.save(), blobs)
    (name,) = blob_names(tmp_path / "state.npz")
    blob = blobs.path(name)
    data = blob.read_bytes()

    blob.write_bytes(data[: len(data) // 2])
    with pytest.raises(SnapshotError, match=rf"state file .*{name}.npz cannot be read \(truncated"):
        read_snapshot(tmp_path / "state.npz")

    arrays = _arrays_of(data)  # one number changed
    key = next(k for k in arrays if k != "header" and arrays[k].dtype == np.float64 and arrays[k].size)
    arrays[key] = arrays[key].copy()
    arrays[key].flat[0] += 1e-12
    _rewrite(blob, arrays)
    with pytest.raises(SnapshotError, match=rf"{name}.npz: checksum mismatch"):
        read_snapshot(tmp_path / "state.npz")

    other = BlobStore(tmp_path / "other", min_bytes=0)  # a valid blob of another map under this name
    _rewrite(blob, encode_state(maps[0]))
    with pytest.raises(SnapshotError, match=rf"blob .*{name}.npz is not the map state file .*state.npz names"):
        read_snapshot(tmp_path / "state.npz")

    blob.unlink()
    with pytest.raises(SnapshotError, match=rf"{name}.npz does not exist"):
        read_snapshot(tmp_path / "state.npz")
    with pytest.raises(SnapshotError, match="has no blob folder"):
        decode_state(_arrays(tmp_path / "state.npz"))
    with pytest.raises(SnapshotError, match="malformed blob name '../x'"):
        other.read("../x", "here")
    (tmp_path / "garbage.npz").write_bytes(b"garbage")
    with pytest.raises(SnapshotError, match="garbage.npz: header cannot be read"):
        blob_names(tmp_path / "garbage.npz")
    with pytest.raises(SnapshotError, match="nothing.npz does not exist"):
        blob_names(tmp_path / "nothing.npz")


def test_the_checksum_is_the_documented_hash_of_every_array_in_memory_order():
    arrays = {
        "a0": np.asfortranarray(np.arange(12.0).reshape(3, 4)),
        "a1": np.arange(24.0).reshape(4, 6)[:, ::2],  # not contiguous: hashed in C order
        "a2": np.array(3.0),
        "a3": np.zeros((0, 3), dtype=np.int8),
    }
    expected = hashlib.sha256(b"tree")
    for key, a in arrays.items():
        fortran = bool(a.flags.f_contiguous and not a.flags.c_contiguous)
        expected.update(f"{key}:{a.dtype.str}:{a.shape}:{fortran}".encode())
        expected.update(a.tobytes(order="A"))
    assert _checksum(b"tree", arrays) == expected.hexdigest()


def test_a_deferred_merge_of_anything_but_maps_is_refused(maps):
    arrays = encode_state(_deferred_joiner(maps, 6).save())
    header = json.loads(bytes(arrays["header"]).decode())
    body = {k: v for k, v in arrays.items() if k != "header"}
    # a deferred merge whose inputs are a string and a map (checksum made valid: only the tree is wrong)
    tree = header["tree"]
    node = _first(tree, "__deferred__")
    node["__deferred__"] = ["a string", node["__deferred__"][1]]
    header["tree"] = tree
    header["sha256"] = _checksum(json.dumps(tree, sort_keys=True, allow_nan=False).encode(), body)
    arrays["header"] = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
    with pytest.raises(SnapshotError, match="a deferred merge of something other than maps"):
        decode_state(arrays)


def _first(node, key):
    """The first dict in a JSON tree that holds ``key`` (depth first)."""
    if isinstance(node, dict):
        if key in node:
            return node
        children = node.values()
    elif isinstance(node, list):
        children = node
    else:
        return None
    for child in children:
        found = _first(child, key)
        if found is not None:
            return found
    return None


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        (lambda h: h.update(version=[FORMAT_VERSION]),
         rf"format version \[{FORMAT_VERSION}\], this build reads version {FORMAT_VERSION}"),
        (lambda h: h.update(version=True), r"format version True"),
        (lambda h: _first(h["tree"], "fields").update(fields=[]), r"malformed state \(AttributeError"),
        (lambda h: h.update(tree={"__tuple__": [float("nan")]}), r"malformed state \(ValueError"),
    ],
    ids=["list-version", "bool-version", "fields-list", "nan"],
)
def test_hostile_trees_are_refused_with_a_snapshot_error(change, expected):
    """Trees a crafted file could hold, with a valid checksum where one can be made."""
    arrays = encode_state(SavedJoiner(Joiner("sequential").state))
    header = json.loads(bytes(arrays["header"]).decode())
    change(header)
    body = {k: v for k, v in arrays.items() if k != "header"}
    with contextlib.suppress(ValueError):  # NaN: no checksum can be made (the tree fails before it is checked)
        header["sha256"] = _checksum(json.dumps(header["tree"], sort_keys=True, allow_nan=False).encode(), body)
    arrays["header"] = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
    with pytest.raises(SnapshotError, match=expected):
        decode_state(arrays)


def test_a_header_nested_too_deep_is_refused_with_a_snapshot_error():
    depth = 100_000
    text = '{"format": "linear_slam_ros.state", "version": 4, "tree": ' + '{"__tuple__": [' * depth + "null" + "]}" * depth + "}"
    with pytest.raises(SnapshotError, match=r"malformed state \(RecursionError"):
        decode_state({"header": np.frombuffer(text.encode(), dtype=np.uint8)})


def test_a_version_5_file_is_read_with_no_feature_re_initialised(maps, caplog):
    from linear_slam_ros.joining.reinit import Relabels

    j = _gated_joiner(maps)
    back = decode_state(_rewritten(j, lambda fields: fields.pop("relabels"), 5))  # what version 5 wrote
    assert back.state.relabels == Relabels() and back.state.variance == j.state.variance
    assert "format version 5" not in caplog.text  # nothing is lost: no warning


def test_a_state_file_that_cannot_be_written_or_names_another_format_is_refused(maps, tmp_path):
    """Branches no test reached (mutation audit, session 26): the node catches only LinearSlamError around a
    periodic snapshot, so a raw OSError would have escaped."""
    j = Joiner("online-dc")
    for seq, m in enumerate(maps[:3], start=1):
        j.offer(m, seq)
    (tmp_path / "file").write_text("not a folder")
    with pytest.raises(SnapshotError, match=r"^cannot write state file .*file/state\.npz: "):
        write_snapshot(tmp_path / "file" / "state.npz", j.save())
    arrays = encode_state(j.save())
    header = json.loads(bytes(arrays["header"]).decode())
    header["format"] = "another_format"
    arrays["header"] = np.frombuffer(json.dumps(header).encode(), dtype=np.uint8)
    with pytest.raises(SnapshotError, match="not a linear_slam_ros state file"):
        decode_state(arrays)


def test_the_blob_cache_never_names_a_dead_map_s_blob_or_a_deleted_file(tmp_path):
    """Its two guards were never exercised (mutation audit, session 26): CPython reuses the id() of a dead map,
    and a blob deleted by ``collect`` must be written again when its map is put again."""
    from linear_slam_ros.core.local_map import POSE, LocalMap

    store = BlobStore(tmp_path / "blobs", min_bytes=0)

    def make(value: float) -> LocalMap:
        return LocalMap(2, 0, 1, np.array([1]), np.array([POSE], np.int8), np.full(3, value), np.eye(3), "m")

    first_map = make(1.0)
    first = store.put(first_map)
    store.sync()
    entry = store._written.pop(id(first_map))
    del first_map
    gc.collect()
    second_map = make(2.0)
    store._written[id(second_map)] = entry  # what id() reuse gives: the dead map's entry under the new map's id
    second = store.put(second_map)
    store.sync()
    assert second != first and store.read(second, "test").x.tolist() == [2.0, 2.0, 2.0]
    assert store.collect(set()) == 2 and not store.path(second).exists()
    again = store.put(second_map)  # the same map, its file gone: written again
    store.sync()
    assert again == second and store.path(again).exists()
