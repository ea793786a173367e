"""``vadgs demo``: train briefly on the bundled sample scene, with the figures a newcomer looks at."""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path

from vadgs.checks import checked, int_field
from vadgs.cli._common import Command, Flag, check_out_dir, metrics_summary, scene_arg
from vadgs.runlock import RunLock
from vadgs.train.run import finish_run


@dataclass(frozen=True)
class DemoCommand(Command):
    """Train briefly on the bundled sample scene; write metrics.json and a PNG panel.

    Running it again replaces the previous demo in ``--out`` (said in one line); a folder holding
    another run needs ``--overwrite``.
    """

    out: str = "outputs/demo"
    """output folder (a previous demo there is replaced)"""
    overwrite: Flag = False
    """--out may hold a run that is not a demo's: its files are removed"""
    iterations: int | None = checked(None, int_field(0, optional=True))
    """override the demo's iteration count (250)"""
    baseline: Flag = False
    """standard densification only (no VAD-GS)"""
    no_progress: Flag = False
    """no progress bar"""

    def main(self) -> int:
        """Train, evaluate, write the figures; 0."""
        from vadgs.runfolder import check_output_folder
        from vadgs.train.checkpoint import describe_run

        out = check_out_dir(self.out, create=False)
        check_output_folder(out, "--out", "vadgs run")
        held = describe_run(out) if out.is_dir() else None
        if held is not None:
            demo = (out / "demo_panel.png").is_file()
            if not (self.overwrite or demo):
                raise ValueError(
                    f"--out {out} holds a run ({held}) that is not a demo's; pass --overwrite to replace it "
                    "or choose another --out"
                )
            print(f"replacing the previous {'demo' if demo else 'run'} in {out} ({held})")
        with RunLock(out, "vadgs demo", log=print):
            if held is not None:
                for name in DEMO_FIGURES:
                    (out / name).unlink(missing_ok=True)
            return self._run(out, overwrite=held is not None)

    def _run(self, out: Path, overwrite: bool) -> int:
        from vadgs.runfolder import record_files
        from vadgs.train.config import TrainConfig
        from vadgs.train.results.evaluate import render_test_view
        from vadgs.train.scenes import BenchmarkRef, prepare_scene
        from vadgs.train.trainer import Trainer
        from vadgs.viz import colorize_depth, image_to_uint8, save_panel

        scene, ref = prepare_scene(BenchmarkRef(str(scene_arg(None)), DEMO_SCALE), out)
        config = TrainConfig.from_dict(DEMO_CONFIG)
        if self.iterations is not None:
            config = config.replace(iterations=self.iterations)
        if not self.baseline:
            from vadgs.train.vad import ReconstructConfig, VisibilityDensifyConfig

            vad = VisibilityDensifyConfig(max_instances=3, reconstruct=ReconstructConfig(max_crop=64))
            config = dataclasses.replace(config, vad=vad)
        t0 = time.perf_counter()
        trainer = Trainer(
            scene, config, out_dir=out, scene_ref=ref, progress=not self.no_progress, overwrite=overwrite
        )
        from vadgs.train.vad import VisibilityAwareDensification

        # config.vad set: the trainer's strategy is the visibility-aware one
        strategy = trainer.strategy if isinstance(trainer.strategy, VisibilityAwareDensification) else None
        snapshots: list[dict] = []  # the largest addition only, for the completion figure
        if strategy is not None:
            strategy.on_addition = lambda snap: snapshots.__setitem__(
                slice(None), [max([*snapshots, snap], key=lambda x: x["added"])]
            )
        result = trainer.train()
        metrics = finish_run(trainer, out, result, not self.no_progress, started=t0)
        view = scene.test_views[len(scene.test_views) // 2]
        r = render_test_view(trainer.model, scene, view, config.raster)
        gtd = scene.load_depths([view])[0, 0]
        vmax = float(gtd[gtd > 0].quantile(0.98))
        pv = next(p for p in metrics["test"]["per_view"] if p["view"] == view)
        png = save_panel(
            [image_to_uint8(r.color[0]), image_to_uint8(scene.load_images([view])[0]),
             colorize_depth(r.raster.depth[0, 0], None, vmax), colorize_depth(gtd, None, vmax)],
            [f"test render ({pv['psnr']:.2f} dB)", "ground truth", "rendered depth", "ground-truth depth"],
            out / "demo_panel.png",
            columns=2,
        )  # fmt: skip
        record_files(out, [png])
        if strategy is not None:
            if snapshots:
                record_files(out, [_completion_panel(trainer, snapshots, out / "demo_completion.png", vmax)])
                print(f"wrote {out / 'demo_completion.png'}")
        print(metrics_summary(metrics))
        print(f"wrote {out / 'metrics.json'} and {png}")
        return 0


def _completion_panel(trainer, snapshots: list, path: Path, vmax: float) -> Path:
    """The instance that got the most new Gaussians: its reference view before and after."""
    from vadgs.viz import colorize_depth, image_to_uint8, save_panel

    snap = max(snapshots, key=lambda s: s["added"])
    scene, view = trainer.scene, snap["view"]
    after = trainer.render_view(view)
    mask = (scene.load_instances([view])[0] == snap["instance"]).float()
    image = scene.load_images([view])[0]
    label, total = completion_label(snap, trainer.state.get("vad_events", []))
    gt = scene.load_depths([view])[0, 0]
    images = [
        image_to_uint8(image * (0.35 + 0.65 * mask)),
        colorize_depth(gt, None, vmax),
        colorize_depth(snap["depth"], None, vmax),
        colorize_depth(after.raster.depth[0, 0].detach(), None, vmax),
    ]
    titles = [
        f"flagged: {label} (view {view})",
        "ground-truth depth",
        f"rendered depth at step {snap['step']}",
        f"after: +{total} MVS Gaussians"
        + (f" ({snap['added']} from this view)" if total != snap["added"] else ""),
    ]
    return save_panel(images, titles, path, columns=2)


#: The figures the demo writes besides the run's files (removed when a demo is replaced).
DEMO_FIGURES = ("demo_panel.png", "demo_completion.png")


def completion_label(snap: dict, events: list[dict]) -> tuple[str, int]:
    """The figure's name of an addition and its instance's total, as the console's event line says them.

    ``("tree 50", 2217)`` for the line's ``tree 50 (+2217)``: the class and instance id of the
    event's log, and the Gaussians the instance got at that event (all its references together;
    ``snap`` is one reference's addition).
    """
    for event in events:
        if event["step"] != snap["step"]:
            continue
        for entry in event["instances"]:
            if entry["instance"] == snap["instance"]:
                return f"{entry['class']} {entry['instance']}", int(entry["added"])
    return f"instance {snap['instance']}", int(snap["added"])


#: The demo's configuration (merged into the TrainConfig defaults): the bundled sample at 120x72,
#: about 14k Gaussians, 250 steps.
DEMO_SCALE = 0.5
DEMO_CONFIG: dict = {
    "iterations": 250,
    "init": {"voxel_size": 0.2, "max_points": 12_000, "max_object_points": 2_000, "sh_degree": 1},
    "strategy": {"refine_start_iter": 60, "refine_every": 40, "refine_stop_iter": 200, "reset_every": 0,
                 "max_gaussians": 25_000},
    "sh_degree_interval": 100,
    "checkpoint_every": 0,
    "log_every": 10,
}  # fmt: skip
