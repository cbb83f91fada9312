"""Re-initialised features: fresh landmark ids, front-end ids, suspect bookkeeping, poses never renamed. (Found
by a mutation audit: each test fails on a mutant the suite let through.)
"""

from __future__ import annotations

import numpy as np

from linear_slam_ros.core.local_map import FEATURE, POSE, LocalMap
from linear_slam_ros.joining.gate import GateResult, VariableNis
from linear_slam_ros.joining.reinit import RELABEL_BASE, Reinitialisation, Relabels, as_joined


def _submap():
    # frame 0, end pose 1, features 7 and 8
    x = np.r_[0.5, 0, 0, 1.0, 2.0, 3.0, 4.0]
    return LocalMap(2, 0, 1, np.array([1, 7, 8]), np.array([POSE, FEATURE, FEATURE], np.int8), x, np.eye(7) * 4.0)


def _split(*vs, rejected=False, variables=None):
    return GateResult(0.99, 50.0, 4, 13.3, split=tuple(vs), rejected=rejected, variables=variables or tuple(vs),
                      submap=None)


F7, F8, P1 = VariableNis(7, FEATURE, 40.0, 2), VariableNis(8, FEATURE, 40.0, 2), VariableNis(7, POSE, 40.0, 3)


def test_a_suspect_id_on_a_pose_is_never_reinitialised():
    r = Relabels(suspects=(7,))
    res = _split(P1)
    assert r.reinitialise(res, _submap()) is res


def test_a_second_reinitialisation_gets_a_fresh_landmark_id():
    r = Relabels(aliases=((5, RELABEL_BASE),), suspects=(7,))
    out = r.reinitialise(_split(F7), _submap())
    assert out.reinitialised == ((7, RELABEL_BASE - 1),)


def test_other_split_variables_stay_marginalised_out():
    r = Relabels(suspects=(7,))
    out = r.reinitialise(_split(F7, F8), _submap())
    assert [v.var_id for v in out.split] == [8]
    assert sorted(out.submap.ids.tolist()) == sorted([1, RELABEL_BASE])


def test_a_relabelled_feature_failing_again_reports_its_front_end_id():
    r = Relabels(aliases=((7, RELABEL_BASE),), suspects=(7,))
    m = r.apply(_submap())  # feature 7 is landmark RELABEL_BASE now
    v = VariableNis(RELABEL_BASE, FEATURE, 40.0, 2)
    out = r.reinitialise(_split(v), m)
    assert out.reinitialised == ((7, RELABEL_BASE - 1),)


def test_a_submap_gated_whole_makes_no_suspect():
    assert Relabels().after(_split(F7, rejected=True)) == Relabels()


def test_suspect_bookkeeping():
    base = Relabels(suspects=(7, 9))
    # 7 split again and re-initialised: no longer suspect; 8 split: suspect; 9 not seen: stays
    res = GateResult(0.99, 50.0, 4, 13.3, split=(F8,), variables=(F7, F8), reinitialised=((7, RELABEL_BASE),))
    after = base.after(res)
    assert after.suspects == (8, 9) and after.aliases == ((7, RELABEL_BASE),)
    # re-initialised 7 is recorded split too? no: 7 passed (renewed), so not suspect
    res2 = GateResult(0.99, 50.0, 4, 13.3, split=(F7,), variables=(F7,), reinitialised=((7, RELABEL_BASE),))
    assert base.after(res2).suspects == (9,)


def test_renewed_suspect_cleared():
    res = GateResult(0.99, 50.0, 4, 13.3, split=(), variables=(VariableNis(RELABEL_BASE, FEATURE, 1.0, 2),),
                     reinitialised=((7, RELABEL_BASE),))
    assert Relabels(suspects=(7,)).after(res).suspects == ()


def test_the_latest_reinitialisation_is_current():
    r = Relabels(aliases=((7, RELABEL_BASE),), suspects=(7,))
    res = GateResult(0.99, 50.0, 4, 13.3, variables=(), reinitialised=((7, RELABEL_BASE - 1),))
    after = r.after(res)
    renamed = after.apply(_submap())
    assert RELABEL_BASE - 1 in renamed.ids.tolist()


def test_as_joined_boundaries():
    m = _submap()
    rec = Reinitialisation(submap=3, robot="", feature=7, landmark=RELABEL_BASE, joined=3)
    out = as_joined([m, m, m], [rec], [2, 3, 4])
    assert [RELABEL_BASE in o.ids.tolist() for o in out] == [False, True, True]
    before = as_joined([m], [], [1], Relabels(((8, RELABEL_BASE - 5),)))
    assert RELABEL_BASE - 5 in before[0].ids.tolist()


def test_pose_ids_are_never_renamed():
    # pose 7 and feature 7 share an id: only the feature is renamed
    x = np.r_[0.5, 0, 0, 1.0, 2.0]
    m = LocalMap(2, 0, 7, np.array([7, 7]), np.array([POSE, FEATURE], np.int8), x, np.eye(5) * 4.0)
    out = Relabels(aliases=((7, RELABEL_BASE),)).apply(m)
    assert out.ids.tolist() == [7, RELABEL_BASE]
    res = Relabels(suspects=(7,)).reinitialise(_split(F7), m)
    assert res.submap.ids.tolist() == [7, RELABEL_BASE - 0]


def test_a_split_pose_sharing_a_renewed_features_id_stays_split():
    x = np.r_[0.5, 0, 0, 3.0, 0, 0, 1.0, 2.0]
    m = LocalMap(2, 0, 1, np.array([1, 7, 7]), np.array([POSE, POSE, FEATURE], np.int8), x, np.eye(8) * 4.0)
    out = Relabels(suspects=(7,)).reinitialise(_split(F7, P1), m)
    assert [(v.var_id, v.kind) for v in out.split] == [(7, POSE)]
    assert out.submap.ids.tolist() == [1, RELABEL_BASE]
