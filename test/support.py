"""Test support shared by the suites: where the benchmark datasets are, reference joiners, and helpers
only the tests use (the inverse pose, dataset writing, result reading, typed global-map accessors)."""

from __future__ import annotations

import contextlib
import os
import tarfile
import tempfile
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np
import numpy.typing as npt
import pytest
import scipy.sparse as sp

from linear_slam_ros.core.errors import DatasetError, InvalidMapError
from linear_slam_ros.core.geometry import angles3, dangles3, drotation, pose_size, rotation, wrap_angle
from linear_slam_ros.core.local_map import POSE, LocalMap
from linear_slam_ros.core.solvers import Backend, solve_dense_spd, solve_sparse_spd
from linear_slam_ros.feature_only.maps import FeatureMap
from linear_slam_ros.io.datasets import MapKind
from linear_slam_ros.joiner.config import OutputFrame
from linear_slam_ros.joiner.joiner import JoinerState, global_result
from linear_slam_ros.joining.divide_conquer import OnlineDCState, online_dc_result, online_dc_step
from linear_slam_ros.joining.pairwise import join_pair, to_end_frame
from linear_slam_ros.joining.sequential import SequentialState, sequential_step

REPO = Path(__file__).resolve().parents[1]


class FakeClock:
    """A clock the test sets by hand (``clock.t = 2.5``), for code that takes a ``clock`` callable (s)."""

    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


def wait_until(condition: Callable[[], bool], timeout: float = 5.0, poll: float = 0.005) -> bool:
    """Poll ``condition`` until it holds or ``timeout`` s pass; return whether it holds (asked once more at the end)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(poll)
    return condition()


def install_prefix(package: str = "linear_slam_ros") -> Path:
    """Where colcon installed ``package``: the repository's own ``install/`` (``make setup``), else,
    in a colcon workspace (``ws/src/linear_slam_ros`` built from ``ws``, its setup sourced), the
    prefix the ament index names; the repository's path when neither is there (the tests that need
    it then say to run ``make setup``)."""
    in_repo = REPO / "install" / package
    if in_repo.is_dir():
        return in_repo
    try:
        from ament_index_python.packages import PackageNotFoundError, get_package_prefix
    except ImportError:
        return in_repo
    try:
        return Path(get_package_prefix(package))
    except PackageNotFoundError:
        return in_repo
DATASETS = Path(os.environ.get("LINEAR_SLAM_DATASETS", REPO.parent / "shared" / "datasets"))
CACHE = REPO / ".cache" / "datasets"
BAGS = REPO / "bags"

# The benchmark datasets committed as bags (bags/README.md): dataset name -> bag folder under bags/.
COMMITTED_BAGS = {
    "VicPark_200_local_maps": "vicpark200",
    "DLR_200_local_maps": "DLR_200_local_maps",
    "8240_data_50_local_maps": "8240_data_50_local_maps",
    "Intel": "Intel",
    "Simu_3D_870_Loop": "Simu_3D_870_Loop",
    "manhattanOlson3500": "manhattanOlson3500",
    "sphere2500": "sphere2500",
}

def committed_bag(name: str) -> Path | None:
    """Return the committed bag of dataset ``name`` (``bags/<bag>``), or None when the repository has none."""
    bag = COMMITTED_BAGS.get(name)
    return BAGS / bag if bag is not None and (BAGS / bag / "metadata.yaml").is_file() else None


def _absent(name: str) -> None:
    """Skip the test: dataset ``name`` is neither in ``DATASETS`` nor committed (fail when ``DATASETS`` is there)."""
    if DATASETS.is_dir():
        pytest.fail(f"benchmark dataset {DATASETS / name}.tar.xz is missing from {DATASETS}")
    pytest.skip(f"needs ../shared/datasets: {name} is not among the committed bags (bags/README.md) and {DATASETS} is absent")


def dataset_source(name: str) -> Path:
    """Return where to read benchmark dataset ``name``: its archive in ``DATASETS`` (``../shared/datasets``)
    when that is there, else its committed bag (the same maps, bit for bit: the same figures).

    Without ``DATASETS``, a dataset with no committed bag skips the test with the reason; with
    ``DATASETS`` present, a missing archive fails it.
    """
    path = DATASETS / f"{name}.tar.xz"
    if path.exists():
        return path
    bag = committed_bag(name)
    if bag is None or DATASETS.is_dir():
        _absent(name)
    assert bag is not None
    return bag


def _reproducible(info: tarfile.TarInfo) -> tarfile.TarInfo:
    info.mtime, info.uid, info.gid, info.uname, info.gname = 0, 0, 0, "", ""
    return info


def dataset_archive(name: str) -> Path:
    """Return a ``.tar.xz`` archive of benchmark dataset ``name``: the one in ``DATASETS`` when that is there,
    else one written once from the committed bag into ``CACHE/from_bags`` (the same maps: 17 significant
    digits read back exactly). Skips or fails as :func:`dataset_source`."""
    source = dataset_source(name)
    if source.suffix == ".xz":
        return source
    archive = CACHE / "from_bags" / f"{name}.tar.xz"
    if not archive.exists():
        from linear_slam_ros.cli.main import read_bag

        dataset = read_bag(source)
        archive.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=archive.parent) as scratch:
            write_dataset(dataset.maps, Path(scratch) / name, dataset.kind)
            partial = archive.with_name(f".{archive.name}.{os.getpid()}")
            with tarfile.open(partial, "w:xz") as tar:  # the same bytes on every machine
                tar.add(Path(scratch) / name, arcname=name, filter=_reproducible)
            # never over another worker's: the unpacked copy records the archive it came from (path, size, time),
            # and a replaced archive is unpacked again under the feet of a worker reading the first one's
            with contextlib.suppress(FileExistsError):
                os.link(partial, archive)
            partial.unlink()
    return archive


def join_sequential_information(maps: Iterable[LocalMap]) -> LocalMap:
    """Join maps one at a time with the paper's information-form step (Sec. 5.1), in end-pose frames.

    The literal recursion of the paper, kept as the reference that
    :mod:`linear_slam_ros.joining.sequential` (covariance form) must equal.
    """
    it = iter(maps)
    try:
        result = to_end_frame(next(it))
    except StopIteration:
        raise InvalidMapError("no local maps to join") from None
    for local_map in it:
        result = join_pair(result, local_map)
    return result


def join_online_dc(maps: Iterable[LocalMap]) -> LocalMap:
    """Join maps with the online divide-and-conquer stack and return the merged result."""
    state = OnlineDCState()
    for m in maps:
        state = online_dc_step(state, m)
    return online_dc_result(state)


def join_sequential(maps: Iterable[LocalMap]) -> LocalMap:
    """Join maps exactly and sequentially; return the global map in the last end pose's frame."""
    state = SequentialState()
    for m in maps:
        state = sequential_step(state, m)
    if state.global_map is None:
        raise InvalidMapError("no local maps to join")
    return state.global_map.to_local_map()


# ---------------------------------------------------------------- helpers only the tests use

FloatArray = npt.NDArray[np.float64]


class InversePose(NamedTuple):
    """The world origin seen from a pose ``T`` (the inverse transform), with its Jacobian.

    Attributes:
        translation: ``(..., d)``.
        angles: ``(..., a)``.
        d_frame: ``(..., d + a, d + a)`` Jacobian with respect to ``T``.
    """

    translation: FloatArray
    angles: FloatArray
    d_frame: FloatArray


def inverse_pose(dim: int, t_frame: FloatArray, ang_frame: FloatArray) -> InversePose:
    """Return the pose of the world origin in the frame of ``T``: ``(-R_T t_T, angles(R_T^T))``."""
    d = dim
    rot = rotation(dim, ang_frame)
    drot = drotation(dim, ang_frame)
    t_inv = -np.einsum("...ij,...j->...i", rot, t_frame)
    p = pose_size(dim)
    jac = np.zeros(t_inv.shape[:-1] + (p, p))
    jac[..., :d, :d] = -rot
    jac[..., :d, d:] = -np.einsum("...kij,...j->...ik", drot, t_frame)
    if dim == 2:
        ang = wrap_angle(-ang_frame)
        jac[..., 2, 2] = -1.0
    else:
        rot_inv = np.swapaxes(rot, -1, -2)
        ang = angles3(rot_inv)
        jac[..., 3:, 3:] = dangles3(rot_inv, np.swapaxes(drot, -1, -2))
    return InversePose(t_inv, ang, jac)


def solve_spd(matrix: FloatArray | sp.spmatrix, rhs: FloatArray, backend: Backend = "auto") -> FloatArray:
    """Solve an SPD system, densely when ``matrix`` is an ``ndarray``, else sparsely."""
    if isinstance(matrix, np.ndarray) or not sp.issparse(matrix):  # an ndarray is never sparse
        return solve_dense_spd(np.asarray(matrix), rhs)
    return solve_sparse_spd(matrix, rhs, backend)


def format_local_map(local_map: LocalMap, kind: MapKind) -> str:
    """Return a map in the benchmark text format (inverse of :func:`parse_local_map_text`)."""
    scalar_ids = []
    for vid, vk, size in zip(local_map.ids.tolist(), local_map.kinds.tolist(), local_map.sizes.tolist(), strict=True):
        tag = -vid if (kind.has_features and vk == POSE) else vid
        scalar_ids.extend([tag] * size)
    lines = [str(local_map.frame_id), str(local_map.state_dim)]
    lines += [f"{i} {v:.17g}" for i, v in zip(scalar_ids, local_map.x.tolist(), strict=True)]
    info = local_map.info_dense()
    lines += [" ".join(f"{v:.17g}" for v in row) for row in info.tolist()]
    return "\n".join(lines) + "\n"


def write_dataset(maps: Sequence[LocalMap], folder: Path, kind: MapKind) -> None:
    """Write maps as ``folder/localmap_<i>.txt``, ``i = 1..N``."""
    folder.mkdir(parents=True, exist_ok=True)
    for i, m in enumerate(maps, start=1):
        (folder / f"localmap_{i}.txt").write_text(format_local_map(m, kind))


def read_rows(path: Path) -> dict[int, FloatArray]:
    """Read a poses or features file back into ``{id: values}``."""
    out: dict[int, FloatArray] = {}
    try:
        for line in Path(path).read_text().splitlines():
            parts = line.split()
            if parts:
                out[int(parts[0])] = np.array([float(v) for v in parts[1:]])
    except (OSError, ValueError) as exc:
        raise DatasetError(f"cannot read {path}: {exc}") from None
    return out


def global_map_of(state: JoinerState, output_frame: OutputFrame | str = OutputFrame.END_POSE) -> LocalMap | None:
    """Return the global pose map in the robocentric end-pose frame or the first pose's frame.

    Raises:
        InvalidMapError: the strategy's maps have no pose frame (see :func:`global_feature_map_of`).
    """
    if state.strategy.result_type is not LocalMap:
        raise InvalidMapError(f"a {state.map_type.value} joiner has no pose frame: use global_feature_map_of")
    result: LocalMap | None = global_result(state, output_frame)
    return result


def global_feature_map_of(state: JoinerState) -> FeatureMap | None:
    """Return the feature-only global map (in the frame of its longest-baseline features).

    Raises:
        InvalidMapError: the strategy does not make feature-only maps.
    """
    if state.strategy.result_type is not FeatureMap:
        raise InvalidMapError(f"a joiner with map_type {state.map_type.value!r} has no feature-only map")
    result: FeatureMap | None = global_result(state)
    return result
