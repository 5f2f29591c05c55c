"""Each suboptimal trajectory kind differs from the optimal plan in the intended way (no simulator)."""
import numpy as np
import pytest

from stages.collect.plans import SUBOPTIMAL_KINDS, Grip, Layout, Move, optimal_plan, suboptimal_plan

DOWN = (0.0, 1.0, 0.0, 0.0)
LAYOUTS = {
    "pick_place": Layout("pick_place", (0.02, 0.05, 0.018), 0.018, DOWN, DOWN, target_p=(0.05, -0.15, 0.0), place_z=0.035),
    "push": Layout("push", (-0.05, 0.0, 0.018), 0.018, DOWN, DOWN, target_p=(0.05, 0.0, 0.018), direction=1.0),
    "pull": Layout("pull", (0.05, 0.0, 0.018), 0.018, DOWN, DOWN, target_p=(-0.05, 0.0, 0.018), direction=-1.0),
}


def _moves(plan, label=None):
    return [s for s in plan if isinstance(s, Move) and (label is None or s.label == label)]


def _dist_to_polyline(p, pts):
    best = np.inf
    for a, b in zip(pts[:-1], pts[1:]):
        ab = b - a
        t = np.clip(np.dot(p - a, ab) / max(np.dot(ab, ab), 1e-12), 0, 1)
        best = min(best, np.linalg.norm(a + t * ab - p))
    return best


@pytest.mark.parametrize("task", sorted(LAYOUTS))
@pytest.mark.parametrize("kind", SUBOPTIMAL_KINDS)
def test_suboptimal_keeps_the_essential_plan(task, kind):
    opt = optimal_plan(LAYOUTS[task])
    sub = suboptimal_plan(opt, kind, np.random.default_rng(0))
    essential = [s for s in sub if isinstance(s, Grip) or s.label == "essential"]
    assert essential == opt  # the essential waypoints, in order, untouched
    assert len(sub) > len(opt)


@pytest.mark.parametrize("task", sorted(LAYOUTS))
def test_waypoint_noise_adds_unrelated_waypoints(task):
    opt = optimal_plan(LAYOUTS[task])
    path = np.array([m.pose[:3] for m in _moves(opt)])
    far = 0
    for seed in range(10):
        noise = _moves(suboptimal_plan(opt, "waypoint_noise", np.random.default_rng(seed)), "noise")
        assert noise
        far += sum(_dist_to_polyline(np.array(m.pose[:3]), path) > 0.03 for m in noise)
        rot_changed = [abs(abs(np.dot(m.pose[3:], DOWN)) - 1) > 1e-4 for m in noise]
        assert any(rot_changed)
    assert far >= 10  # intermediate waypoints off the essential path, not on it


@pytest.mark.parametrize("task", sorted(LAYOUTS))
def test_interpolate_adds_points_on_the_essential_segments(task):
    opt = optimal_plan(LAYOUTS[task])
    sub = suboptimal_plan(opt, "interpolate", np.random.default_rng(0))
    path = np.array([m.pose[:3] for m in _moves(opt)])
    interp = _moves(sub, "interp")
    assert len(interp) == 2 * (len(path) - 1)
    assert all(_dist_to_polyline(np.array(m.pose[:3]), path) < 1e-9 for m in interp)


@pytest.mark.parametrize("task", sorted(LAYOUTS))
def test_grasp_disturb_perturbs_near_grasp_and_place(task):
    opt = optimal_plan(LAYOUTS[task])
    roles = {"pick_place": ("grasp", "place"), "push": ("contact", "slide"), "pull": ("contact", "slide")}[task]
    sub = suboptimal_plan(opt, "grasp_disturb", np.random.default_rng(3))
    path = np.array([m.pose[:3] for m in _moves(opt)])
    for i, step in enumerate(sub):
        if isinstance(step, Move) and step.label == "disturb":
            nxt = sub[i + 1]
            assert nxt.role in roles  # right before a grasp/place (contact / slide end) waypoint
            p = np.array(step.pose[:3])
            if nxt.role == "slide":  # a wobble off the slide line, at the object's height
                assert 0 < _dist_to_polyline(p, path) < 0.01 and p[2] == nxt.pose[2]
            else:
                d = np.linalg.norm(p - np.array(nxt.pose[:3]))
                assert 0.005 < d < 0.05  # small, but a real disturbance
    assert len(_moves(sub, "disturb")) == 2


def test_unknown_kind_errors():
    with pytest.raises(ValueError, match="unknown trajectory kind"):
        suboptimal_plan(optimal_plan(LAYOUTS["push"]), "zigzag", np.random.default_rng(0))


@pytest.mark.parametrize("task", sorted(LAYOUTS))
def test_near_miss_ends_beside_the_goal_after_the_same_approach(task):
    opt = optimal_plan(LAYOUTS[task])
    for seed in range(10):
        miss = suboptimal_plan(opt, "near_miss", np.random.default_rng(seed))
        assert len(miss) == len(opt) and all(type(a) is type(b) for a, b in zip(miss, opt))
        same = [a == b for a, b in zip(miss, opt)]
        roles = [s.role for s in opt if isinstance(s, Move)]
        first_changed = next(i for i, ok in enumerate(same) if not ok)
        assert all(same[:first_changed])  # approach and grasp / contact untouched
        end_opt, end_miss = np.array(_moves(opt)[-2].pose[:3]), np.array(_moves(miss)[-2].pose[:3])
        if "slide" in roles:  # the slide stops short along its own direction
            contact = np.array(next(m for m in _moves(opt) if m.role == "contact").pose[:3])
            travelled = np.linalg.norm(end_miss - contact) / np.linalg.norm(end_opt - contact)
            assert 0.15 - 1e-9 <= travelled <= 0.6 + 1e-9
        else:  # released 8-13 cm sideways, at the same height
            assert 0.08 - 1e-9 <= np.linalg.norm(end_miss[:2] - end_opt[:2]) <= 0.13 + 1e-9
            assert end_miss[2] == pytest.approx(end_opt[2])


@pytest.mark.parametrize("task", sorted(LAYOUTS))
def test_grasp_miss_lands_beside_the_object_and_keeps_the_rest(task):
    from stages.common.proprio import quat_to_matrix

    opt = optimal_plan(LAYOUTS[task])
    roles = [s.role for s in _moves(opt)]
    moved = ("pre", "contact", "slide", "retreat") if "slide" in roles else ("pre", "grasp", "lift")
    sides = set()
    for seed in range(10):
        miss = suboptimal_plan(opt, "grasp_miss", np.random.default_rng(seed))
        assert len(miss) == len(opt) and all(type(a) is type(b) for a, b in zip(miss, opt))
        shifts = [np.array(b.pose[:3]) - np.array(a.pose[:3]) for a, b in zip(_moves(opt), _moves(miss))]
        for a, b, d in zip(_moves(opt), _moves(miss), shifts):
            assert b.pose[3:] == a.pose[3:] and b.role == a.role
            if a.role not in moved:
                assert np.allclose(d, 0.0), a.role  # carry, place, retreat (pick) untouched
        d = shifts[roles.index(moved[1])]  # the grasp / contact waypoint
        assert d[2] == 0.0 and 0.05 - 1e-9 <= np.linalg.norm(d) <= 0.065 + 1e-9
        assert all(np.allclose(shifts[roles.index(r)], d) for r in moved)  # one rigid sideways shift
        if "slide" in roles:
            assert d[0] == 0.0  # across the slide, not along it
        else:  # across the fingers' closing direction (the grasp frame's y axis)
            closing = quat_to_matrix(_moves(opt)[roles.index("grasp")].pose[3:])[:, 1]
            assert abs(np.dot(d / np.linalg.norm(d), closing)) < 1e-6
        sides.add(np.sign(d[np.argmax(np.abs(d))]))
    assert sides == {-1.0, 1.0}  # both sides of the object



def test_the_grasp_frame_axes_the_plan_reads():
    """grasp_miss_plan reads the grasp frame's x axis as quat_to_matrix's column 0 (wxyz quaternions)."""
    from stages.common.proprio import quat_to_matrix

    half = np.sqrt(0.5)
    q = (half, 0.0, 0.0, half)  # +90 degrees about z: x -> y, y -> -x
    assert np.allclose(quat_to_matrix(q)[:, 0], [0, 1, 0]) and np.allclose(quat_to_matrix(q)[:, 1], [-1, 0, 0])
    assert np.allclose(quat_to_matrix(DOWN)[:, 2], [0, 0, -1])  # 180 degrees about x: z -> -z


@pytest.mark.parametrize("task", sorted(LAYOUTS))
def test_recover_makes_a_mistake_then_completes_the_optimal_plan(task):
    opt = optimal_plan(LAYOUTS[task])
    moves = {m.role: m for m in _moves(opt)}
    head = opt.index(moves["pre"]) + 1
    target = np.array(moves["contact" if "slide" in moves else "grasp"].pose[:3])
    variants = set()
    for seed in range(12):
        rec = suboptimal_plan(opt, "recover", np.random.default_rng(seed))
        assert rec[:head] == opt[:head] and rec[-(len(opt) - head):] == opt[head:]  # the optimal plan around it
        middle = rec[head:len(rec) - (len(opt) - head)]
        labels = [s.label for s in middle]
        n_err = labels.count("err")
        assert n_err and labels[:n_err] == ["err"] * n_err  # the mistake first ...
        back = middle[n_err:]
        assert back and all(s.label == "recover" for s in back if not (isinstance(s, Move) and s.role == "pre"))
        err_moves = [np.array(s.pose[:3]) for s in middle[:n_err] if isinstance(s, Move)]
        low = err_moves[-1]  # where the mistake is made
        offset = low - target
        grips = [(s.label, s.value) for s in middle if isinstance(s, Grip)]
        if "slide" in moves:  # push / pull: the closed fingers come down beside the contact, no grip change
            assert not grips and offset[0] == 0.0 and offset[2] == 0.0 and 0.05 - 1e-9 <= abs(offset[1]) <= 0.065 + 1e-9
            assert np.allclose(err_moves[0], low + [0, 0, 0.08])  # approached from straight above
            assert np.allclose(back[0].pose[:3], low + [0, 0, 0.08]) and back[-1] == moves["pre"]  # up, then pre
            variants.add("beside")
        else:  # pick: close where it should not, then reopen first of all
            assert grips == [("err", -1.0), ("recover", 1.0)] and isinstance(back[0], Grip)
            if np.allclose(offset[:2], 0.0):  # early close above the grasp, then straight on down to it
                assert 0.025 - 1e-9 <= offset[2] <= 0.05 + 1e-9 and len(back) == 1
                variants.add("above")
            else:  # beside the object at its height, approached and left straight above
                assert offset[2] == pytest.approx(0.0) and 0.05 - 1e-9 <= np.linalg.norm(offset) <= 0.065 + 1e-9
                assert np.allclose(err_moves[0], low + [0, 0, 0.08])
                assert np.allclose(back[1].pose[:3], low + [0, 0, 0.08]) and back[-1] == moves["pre"]
                variants.add("beside")
    assert variants == ({"beside"} if "slide" in moves else {"above", "beside"})


def test_recovery_episodes_are_planned_in_ind_scenes_only_and_leave_the_others_unchanged(tmp_path):
    from stages.collect import Config, plan_jobs, scene_catalog

    def episodes(cfg):
        return [e for job in plan_jobs(cfg, scene_catalog(cfg), tmp_path) for e in job["episodes"]]

    base = Config(tasks=("push",), ind_scenes=2, ood_scenes=1)
    plain, with_recovery = episodes(base), episodes(base.model_copy(update={"recover_per_scene": 2}))
    recover = [e for e in with_recovery if e["kind"] == "recover"]
    assert not any(e["kind"] == "recover" for e in plain)
    assert len(recover) == 2 * 2 and {e["scene"]["split"] for e in recover} == {"ind"}
    # every other episode is the one planned without them: kind, scene, seed, id and replay flag
    assert [e for e in with_recovery if e["kind"] != "recover"] == plain
    seeds = [e["seed"] for e in with_recovery]
    assert len(set(seeds)) == len(seeds)
