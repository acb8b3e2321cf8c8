"""evaluate_run on a synthetic run directory, and the report built from several runs."""

import json
import re

import matplotlib.pyplot as plt
import numpy as np
import pytest

from area3d_eval.evaluate import default_checkpoints, evaluate_run, image_metrics, reference_images
from area3d_eval.render import MeshRenderer
from area3d_eval.report import aggregate, write_report
from area3d_eval.report_figures import hard_region_text
from area3d_eval.rundir import stopped_early
from area3d_eval.synthetic import SyntheticRenderer, SyntheticScene, hemisphere_views, make_run

SMALL = {
    "renderer_factory": SyntheticRenderer,
    "eval_width": 64,
    "eval_height": 48,
    "num_surface_points": 4000,
}


@pytest.fixture(scope="module")
def scene():
    return SyntheticScene(subdivisions=3)


def test_default_checkpoints_cover_initial_views_every_fourth_60_percent_and_the_last():
    assert default_checkpoints(29, 4) == [4, 8, 12, 16, 17, 20, 24, 28, 29]
    assert default_checkpoints(25, 4) == [4, 8, 12, 15, 16, 20, 24, 25]
    assert default_checkpoints(40, 15) == [4, 8, 12, 15, 16, 20, 24, 28, 32, 36, 40]
    assert default_checkpoints(3, 4) == [2, 3]


def test_the_ground_truth_mesh_rendered_at_eval_views_scores_perfectly(scene):
    K, images, masks = reference_images(scene, SyntheticRenderer, 64, 48, 90.0)
    assert len(images) == len(scene.eval_views) and all(m.any() for m in masks)
    scores = image_metrics(
        MeshRenderer(scene.ground_truth_mesh()), K, scene.eval_views, images, masks
    )
    assert scores["psnr"] == 100.0 and scores["psnr_roi"] == 100.0  # identical images, capped
    assert scores["ssim"] == pytest.approx(1.0) and scores["ssim_roi"] == pytest.approx(1.0)


def test_evaluate_run_writes_metrics_after_each_checkpoint(tmp_path, scene):
    # 320 x 240: at 160 x 120 the object spans a few hundred pixels, most of them within the
    # sensor model's two pixels of a depth edge (confidence 0.2), below the TSDF's weight floor
    run = make_run(
        tmp_path / "run", scene, policy="random", seed=0, budget=5, width=320, height=240
    )
    result = evaluate_run(run, scene, **SMALL)
    written = json.loads((run / "metrics.json").read_text())
    assert [row["num_views"] for row in written["curve"]] == [4, 5, 8, 9]  # 5: 60 % of 9
    assert written["final"]["num_views"] == 9 and written["policy"] == "random"
    assert (run / "eval" / "reconstruction.ply").is_file() and (
        run / "eval" / "gt_sample.npy"
    ).is_file()
    final = result["final"]
    # the object is seen from all sides but not from below: most of the surface, accurately
    assert 0.5 < final["completion"] < 1.0 and final["accuracy"] < 0.005
    assert 0.0 < final["ssim"] <= 1.0 and np.isfinite(final["psnr"])
    assert result["curve"][-1]["completion"] >= result["curve"][0]["completion"] - 0.02


def test_report_has_a_row_per_policy_and_every_figure_it_links(tmp_path, scene):
    runs = []
    for policy, seeds, elevation in (("uniform", (0, 1), 60.0), ("area3d", (0,), 15.0)):
        for seed in seeds:
            poses = hemisphere_views(
                scene.center,
                scene.view_radius,
                np.array([45.0, 135.0]) + 10 * seed,
                np.full(2, elevation),
            )
            run = make_run(
                tmp_path / f"{policy}_{seed}",
                scene,
                policy=policy,
                seed=seed,
                budget=2,
                width=80,
                height=60,
                poses=poses,
            )
            evaluate_run(run, scene, **SMALL)
            runs.append(run)
    x, y, z = (a.ravel() for a in np.meshgrid(*[np.linspace(-0.2, 0.2, 6)] * 3, indexing="ij"))
    u = np.exp(-(x**2 + y**2) * 20)
    # the final grid's hard voxels: two neighbours at one corner, one at the opposite corner
    hard = np.zeros_like(u)
    corner = (x == x.min()) & (y == y.min())
    hard[corner & (z <= np.unique(z)[1])] = 1.0
    hard[(x == x.max()) & (y == y.max()) & (z == z.max())] = 1.0
    for name, scale, flags in (("grid_initial.npz", 1.0, 0 * u), ("grid_final.npz", 0.3, hard)):
        np.savez(
            runs[0] / name,
            x=x,
            y=y,
            z=z,
            uncertainty=u * scale,
            geometric=u,
            semantic=u,
            occupancy=0 * u,
            hard=flags,
        )

    # the area3d run ended before its budget: the report says so, with the planner's reason
    episode_json = runs[2] / "episode.json"
    saved = json.loads(episode_json.read_text())
    saved["budget"] = len(saved["views"]) + 3
    saved["stopped_early"] = stopped_early(3, "budget: all 9 views are spent")
    # and its VLM failed: the regions came from the fallback, which the report says
    why = "cannot reach the VLM server at http://127.0.0.1:9/v1/chat/completions"
    saved["semantics"] = {"backend": "openai", "fallback_used": "heuristic", "error": why}
    episode_json.write_text(json.dumps(saved))

    md_path, html_path = write_report(runs, tmp_path / "report", evaluate_missing=False)
    md, page = md_path.read_text(), html_path.read_text()
    stopped = (
        f"Stopped early after {len(saved['views'])} of {len(saved['views']) + 3} views: the "
        "planner returned no view with 3 left (budget: all 9 views are spent)."
    )
    assert md.count("Stopped early") == 1 and stopped in md and stopped in page
    fell_back = (
        f"Semantic regions from the `heuristic` fallback, not from the `openai` backend: {why}."
    )
    assert md.count("Semantic regions from") == 1 and fell_back in md
    assert (
        fell_back.replace("`heuristic`", "<code>heuristic</code>").replace(
            "`openai`", "<code>openai</code>"
        )
        in page
    )  # the HTML shows the Markdown's code as code

    rows = [line for line in md.splitlines() if line.startswith("| ")]
    starts = [i for i, r in enumerate(rows) if r.startswith("| Policy |")]
    assert len(starts) == 3  # the headline table, the whole-image table, the views to reach
    headline, second, fewer = rows[: starts[1]], rows[starts[1] : starts[2]], rows[starts[2] :]
    assert headline[0].startswith("| Policy | synthetic_object: Comp. ratio")
    # headline table: PSNR / SSIM on the region; the whole-image ones in a second table
    assert "PSNR region [dB]" in headline[0] and "whole image" not in headline[0]
    assert "PSNR whole image [dB]" in second[0] and "Comp. ratio" not in second[0]
    # the Chamfer distance's two halves, in mm, beside the whole-image figures
    assert "Accuracy [mm]" in second[0] and "Completeness [mm]" in second[0]
    columns = [c.strip() for c in second[0].strip().strip("|").split("|")]
    accuracy = columns.index("synthetic_object: Accuracy [mm] ↓")
    cells = [c.strip() for c in next(r for r in second if r.startswith("| uniform |")).split("|")]
    assert 0 < float(cells[1 + accuracy].split("±")[0].strip("* ")) < 50
    for table in (headline, second):
        assert sum(r.startswith("| uniform |") for r in table) == 1
        assert sum(r.startswith("| area3d |") for r in table) == 1
    # the views each row took to reach uniform's final mean completion, from the runs' curves
    assert "## Views to reach `uniform`'s final completion" in md
    assert "<h2>Views to reach <code>uniform</code>'s final completion</h2>" in page
    curves = [json.loads((r / "metrics.json").read_text())["curve"] for r in runs]
    target = np.mean([curve[-1]["completion"] for curve in curves[:2]])
    for name, curve in (("area3d", curves[2]), ("uniform", None)):
        if curve is None:  # uniform's own: the mean of its two seeds per checkpoint
            curve = [
                {"num_views": a["num_views"], "completion": (a["completion"] + b["completion"]) / 2}
                for a, b in zip(*curves[:2], strict=True)
            ]
        reached = [p["num_views"] for p in curve if p["completion"] >= target]
        last = curve[-1]["num_views"]
        expected = (
            f"{min(reached)} of {last} ({100 * min(reached) / last:.0f} %)"
            if reached
            else f"not reached ({curve[-1]['completion']:.3f} < {target:.3f})"
        )
        assert next(r for r in fewer if r.startswith(f"| {name} |")) == f"| {name} | {expected} |"
    uniform_row = next(r for r in headline if r.startswith("| uniform |"))
    assert "±" in uniform_row  # two seeds: mean ± std
    assert "How to read this report" in md and "How to read this report" in page
    assert (
        "<table>" in page
        and "<td class='policy'>uniform</td>" in page
        and "<td class='policy'>area3d</td>" in page
    )

    links = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", md)
    srcs = re.findall(r"<img src='([^']+)'", page)
    assert sorted(links) == sorted(srcs)
    # curves, views per run, one uncertainty figure, timings, and each run's mesh seen around
    meshed = [r for r in runs if (r / "eval" / "reconstruction.ply").is_file()]
    assert meshed and len(links) == 5 + 3 + 1 + 1 + len(meshed)
    mesh_figures = [link for link in links if link.endswith("_mesh.png")]
    assert len(mesh_figures) == len(meshed) and md.count("## Reconstruction") == 1
    image = plt.imread(md_path.parent / mesh_figures[0])[..., :3]
    assert (image.max(axis=-1) - image.min(axis=-1)).max() > 0.1  # colour, not a blank page
    assert any("psnr_roi" in link for link in links) and not any(
        link.endswith("_psnr.png") for link in links
    )  # the curves show the region's PSNR, not the whole image's
    for link in links:
        assert (md_path.parent / link).is_file(), link
    assert any("uncertainty" in link for link in links)
    # the final grid's hard regions, in the run's text: 2 regions of 3 voxels (8 cm apart)
    sentence = "Hard regions in the final grid: 2 (3 hard voxels of 8 cm; the largest, 2 voxels"
    assert sentence in md and sentence in page
    assert "around (-0.20, -0.20, -0.16) m)" in md

    table = {(r["scene"], r["policy"]): r for r in aggregate(runs)}
    assert (
        table[("synthetic_object", "uniform")]["runs"] == 2
        and table[("synthetic_object", "area3d")]["runs"] == 1
    )
    finals = [json.loads((r / "metrics.json").read_text())["final"]["fscore"] for r in runs[:2]]
    assert table[("synthetic_object", "uniform")]["fscore"] == pytest.approx(np.mean(finals))


def test_a_scene_given_by_path_is_named_by_its_file_stem_never_by_the_path(tmp_path, scene):
    scenes_dir = tmp_path / "generated"
    runs = []
    for i, (path, policy) in enumerate(
        [
            ("kitchen/shelf_wall_s0.xml", "uniform"),
            ("kitchen/shelf_wall_s0.xml", "area3d"),
            ("hall/shelf_wall_s0.xml", "uniform"),  # another file of the same stem
            ("thin/thin_objects_s1.xml", "uniform"),
        ]
    ):
        run = make_run(tmp_path / f"run{i}", scene, policy=policy, budget=1, width=80, height=60)
        episode = json.loads((run / "episode.json").read_text())
        episode["scene"] = str(scenes_dir / path)  # as `area3d run --scene PATH` writes it
        (run / "episode.json").write_text(json.dumps(episode))
        evaluate_run(run, scene, **SMALL)
        runs.append(run)
    rows = aggregate(runs)
    assert sorted({r["scene_name"] for r in rows}) == [
        "shelf_wall_s0 (hall)",
        "shelf_wall_s0 (kitchen)",
        "thin_objects_s1",
    ]
    assert all(r["scene"].startswith(str(scenes_dir)) for r in rows)  # the path stays for loading
    md_path, html_path = write_report(runs, tmp_path / "report", evaluate_missing=False)
    md, page = md_path.read_text(), html_path.read_text()
    for text in (md, page):
        assert str(tmp_path) not in text and "generated" not in text and ".xml" not in text
    header = next(line for line in md.splitlines() if line.startswith("| Policy |"))
    assert "| thin_objects_s1: Comp. ratio" in header
    assert "| shelf_wall_s0 (kitchen): Comp. ratio" in header
    assert "### thin_objects_s1 / uniform / seed 0" in md  # the chosen views' titles
    assert "<h3>thin_objects_s1</h3>" in page  # the curves' section
    figures = [p.name for p in (tmp_path / "report" / "figures").iterdir()]
    assert any(name.startswith("curve_thin_objects_s1_") for name in figures)
    assert not any("generated" in name or "xml" in name for name in figures)


def test_held_out_references_are_lit_by_the_scene_lights_not_a_headlight():
    from area3d_eval.evaluate import _sim_renderer
    from sim_bridge.scenes import load_scene

    sim_scene = load_scene("five_objects")
    made = []

    def factory(*args):
        made.append(_sim_renderer(*args))
        return made[-1]

    _, images, masks = reference_images(sim_scene, factory, 80, 60, 90.0)
    headlight = made[0].model.vis.headlight
    assert made[0].scene_lit and np.all(headlight.diffuse == 0) and np.all(headlight.specular == 0)
    roi_pixels = np.concatenate([img[m] for img, m in zip(images, masks, strict=True)])
    assert len(roi_pixels) > 1000 and roi_pixels.mean() > 40  # lit, not black
    assert (roi_pixels.max(axis=1) < 10).mean() < 0.05


def test_an_estimated_depth_run_is_reconstructed_from_perceptions_depth(tmp_path, scene):
    from area3d_eval.rundir import (
        EPISODE_FILE,
        frame_files,
        read_frame,
        write_frame,
    )

    run = make_run(
        tmp_path / "run", scene, policy="area3d", seed=0, budget=4, width=160, height=120
    )
    for path in frame_files(run):  # perception "estimated" every surface 3 cm too far
        f = read_frame(path)
        confidence = np.ones_like(f.depth)
        write_frame(
            run, f.index, f.rgb, f.depth, f.K, f.T_world_cam, f.stamp_ns, f.depth + 0.03, confidence
        )
    sensor = evaluate_run(run, scene, write=False, **SMALL)
    episode = json.loads((run / EPISODE_FILE).read_text())
    (run / EPISODE_FILE).write_text(json.dumps({**episode, "depth_source": "estimated"}))
    estimated = evaluate_run(run, scene, write=False, **SMALL)  # the episode's choice
    assert sensor["depth_source"] == "sensor" and estimated["depth_source"] == "estimated"
    assert estimated["final"]["accuracy"] > sensor["final"]["accuracy"] + 0.01, (sensor, estimated)


def test_hard_voxels_are_picked_from_a_grid_by_height_and_absent_grids_have_none():
    from area3d_eval.plots import hard_voxels_xy

    grid = {
        "x": np.array([0.0, 0.1, 0.2, 0.3]),
        "y": np.array([1.0, 1.1, 1.2, 1.3]),
        "z": np.array([0.5, 0.5, 0.6, 0.5]),
        "hard": np.array([1.0, 0.0, 1.0, 1.0], np.float32),
    }
    x, y = hard_voxels_xy(grid)
    np.testing.assert_array_equal(x, [0.0, 0.2, 0.3])
    x, y = hard_voxels_xy(grid, 0.5)
    np.testing.assert_array_equal(y, [1.0, 1.3])
    assert hard_voxels_xy({k: v for k, v in grid.items() if k != "hard"})[0].size == 0


@pytest.mark.parametrize(
    ("voxel", "origin"),
    [
        (0.01, (-0.31, 0.17, 0.05)),
        (0.05, (-0.31, 0.17, 0.05)),
        (0.025, (0, 0, 0)),
        (0.01, (70, 3, 0)),
    ],
)
def test_the_hard_region_sentence_names_the_voxel_size_of_a_grid_saved_in_float32(voxel, origin):
    # centres saved as float32 (as the planner's PointCloud2 and grid files hold them): their
    # gaps are the voxel size only to float32 precision (0.00999999 m for 1 cm; 70 m from the
    # origin a gap is 0.0099945 or 0.0100021 m)
    ijk = np.stack(np.meshgrid(*[np.arange(6)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    xyz = ((ijk + 0.5) * voxel + np.array(origin, float)).astype(np.float32)
    hard = np.zeros(len(xyz), np.uint8)
    hard[[0, 1]] = 1  # two face neighbours: one region
    grid = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "hard": hard}
    grid["uncertainty"] = np.ones(len(xyz), np.float32)
    text = hard_region_text(grid)
    assert f"(2 hard voxels of {voxel * 100:g} cm; the largest, 2 voxels" in text, text


def test_region_psnr_splits_into_empty_pixels_and_the_reconstructed_ones(scene):
    # a reconstruction without the half of the surface at x > 0: the held-out views that saw it
    # show black there (no surface); the pixels it keeps are the ground truth's own colours
    K, images, masks = reference_images(scene, SyntheticRenderer, 64, 48, 90.0)
    full = scene.ground_truth_mesh()
    centres = full.triangles_center
    half = full.copy()
    half.update_faces(centres[:, 0] <= 0.0)
    whole = image_metrics(MeshRenderer(full), K, scene.eval_views, images, masks)
    cut = image_metrics(MeshRenderer(half), K, scene.eval_views, images, masks)
    assert whole["roi_unreconstructed"] == 0.0 and whole["psnr_roi_reconstructed"] == 100.0
    # every ROI pixel whose ray met a removed face and nothing behind it is empty now
    empty = sum(
        int(np.count_nonzero(m & ~np.isfinite(MeshRenderer(half).render(K, T, 64, 48)[1])))
        for T, m in zip(scene.eval_views, masks, strict=True)
    ) / sum(int(m.sum()) for m in masks)
    assert 0.05 < cut["roi_unreconstructed"] == pytest.approx(empty)
    # the empty pixels, black against a lit surface, are what lowers the region PSNR
    assert cut["psnr_roi"] < cut["psnr_roi_reconstructed"]


def test_runs_of_one_policy_with_other_budgets_are_rows_of_their_own(tmp_path, scene):
    runs = []
    for name, budget, seed in (("a", 2, 0), ("b", 2, 1), ("c", 3, 0)):
        poses = hemisphere_views(
            scene.center, scene.view_radius, np.linspace(0.0, 240.0, budget), np.full(budget, 30.0)
        )
        run = make_run(
            tmp_path / name, scene, policy="uniform", seed=seed, budget=budget,
            width=80, height=60, poses=poses,
        )  # fmt: skip
        evaluate_run(run, scene, **SMALL)
        runs.append(run)
    rows = {row["label"]: row for row in aggregate(runs)}
    # two seeds of 2 views in one row; the run of 3 views is not averaged into it
    assert set(rows) == {"uniform (2 views)", "uniform (3 views)"}
    assert rows["uniform (2 views)"]["runs"] == 2 and rows["uniform (3 views)"]["runs"] == 1
    assert all(row["policy"] == "uniform" for row in rows.values())
    single = json.loads((runs[2] / "metrics.json").read_text())["final"]["completion"]
    assert rows["uniform (3 views)"]["completion"] == pytest.approx(single)
    # runs alike keep the policy's name alone
    assert [row["label"] for row in aggregate(runs[:2])] == ["uniform"]


def test_one_hard_voxel_is_counted_in_the_singular():
    ijk = np.stack(np.meshgrid(*[np.arange(4)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    xyz = ((ijk + 0.5) * 0.01).astype(np.float32)
    hard = np.zeros(len(xyz), np.uint8)
    hard[0] = 1
    grid = {"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2], "hard": hard}
    grid["uncertainty"] = np.ones(len(xyz), np.float32)
    text = hard_region_text(grid)
    assert "1 (1 hard voxel of 1 cm; the largest, 1 voxel, around" in text, text


def test_the_html_report_renders_the_markdown_emphasis_and_code_of_its_text():
    from area3d_eval.report import _inline

    said = _inline("*Completion ratio* of `heuristic` <b> 2 * 3 * 4, a_b*c")
    assert "<em>Completion ratio</em>" in said and "<code>heuristic</code>" in said
    assert "&lt;b&gt;" in said  # escaped before any markup is added
    assert "2 * 3 * 4" in said and "a_b*c" in said  # a product and a name stay as they are


def test_the_curves_mark_whole_numbers_of_views_only(tmp_path, monkeypatch):
    import area3d_eval.plots as plots

    figures = []
    monkeypatch.setattr(plots, "_save", lambda fig, path: figures.append(fig) or path)
    rows = [{"num_views": n, "completion": n / 10} for n in (4, 5, 6)]
    plots.plot_metric_curves({"area3d": [rows]}, "completion", tmp_path / "c.png")
    ticks = figures[0].axes[0].get_xticks()
    assert len(ticks) >= 2 and np.allclose(ticks, np.round(ticks)), ticks


def test_the_grid_figure_shows_each_columns_mean_with_the_empty_voxels_as_zero(
    tmp_path, monkeypatch
):
    """Every column through an object holds its never-seen inside at full uncertainty: a maximum
    along z stayed at 1 there however well the surface was known; the mean falls as it is. The
    published grid leaves empty voxels out: they count as 0, and a column of none stays blank."""
    import area3d_eval.plots as plots

    vol = np.full((2, 2, 4), np.nan)
    vol[0, 0] = [1.0, np.nan, 0.2, np.nan]  # an unseen inside, an empty voxel, a known surface
    vol[1, 0] = [1.0, 1.0, 1.0, 1.0]
    vol[0, 1, 3] = 0.4
    mean = plots.column_mean(vol)
    assert mean[0, 0] == pytest.approx(0.3) and mean[1, 0] == 1.0 and mean[0, 1] == 0.1
    assert np.isnan(mean[1, 1])
    figures = []
    monkeypatch.setattr(plots, "_save", lambda fig, path: figures.append(fig) or path)
    x, y, z = (
        a.ravel() for a in np.meshgrid([0.0, 0.1], [0.0, 0.1], [0.0, 0.1, 0.2, 0.3], indexing="ij")
    )
    grid = {"x": x, "y": y, "z": z, "uncertainty": vol.ravel(), "hard": np.zeros(x.size)}
    grid["hard"][0] = 1
    plots.plot_grid_slices(grid, grid, tmp_path / "g.png")
    panel = figures[0].axes[1]
    assert panel.get_title() == "before: mean over z\n1 hard voxels (cyan)"
    np.testing.assert_allclose(panel.get_images()[0].get_array().T, mean)
