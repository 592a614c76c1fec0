"""Which results a workflow run produces, from workflow/config.yaml (paths relative to the work directory, in the
results tree of workflow/layout.py).

    avatars: recipe final (every subject's avatar, from the final recipe's model) | base (the ablation fine-tunes:
        the 14 initialisations of `ablation_subjects`; the interpolation variants <init>_frames<b|c>);
        <init>_seed<k>: the same run with seed k (k = 1 .. seeds-1; seed 0 is the plain folder)
    pretrain/<final recipe>_<R>px: the final recipe continued at resolution R (the scale's `resolution_tiers`), and
        the avatars/<subject>/final/<final recipe>_<R>px avatars from it
    sweeps/<sweep>/{table.md,table.csv,figure.png}, sweeps/<sweep>/<point>/{model.pt,train.json,eval.json}
"""
from __future__ import annotations

import glob
import sys
from dataclasses import dataclass
from pathlib import Path

from avatarlab.workflow.layout import VARIANTS, AvatarKey, ResultsTree, logs_root, results_root
from avatarlab.workflow.sweeps import SWEEP_DIR, load_sweeps

SPEECH_MODEL_DIR = Path(__file__).resolve().parents[3] / "conf" / "speech_model"


def speech_model_kind(name: str) -> str | None:
    """conf/speech_model/<name>.yaml's `model` (lstm: audio in, window: phoneme labels in), through its defaults."""
    import yaml

    spec = yaml.safe_load((SPEECH_MODEL_DIR / f"{name}.yaml").read_text()) or {}
    if "model" in spec:
        return spec["model"]
    parents = [d for d in spec.get("defaults", []) if isinstance(d, str) and d != "_self_"]
    return speech_model_kind(parents[0]) if parents else None


def resolution_tiers(final_recipe: str, scale: dict) -> list[ResolutionTier]:
    """The scale's `resolution_tiers` (e.g. [256, 512] at paper scale; none at smoke and tiny) as a chain from the
    final recipe's model: each tier continues the previous one after `resolution_tier_iterations`."""
    sizes = [int(r) for r in (scale.get("resolution_tiers") or [])]
    if not sizes:
        return []
    bad = [r for r in sizes if r % 8 or r <= int(scale["pretrain_image_size"])]
    if bad or sizes != sorted(set(sizes)):
        raise ValueError(f"conf/scale/{scale.get('name')}.yaml: resolution_tiers {sizes} must rise above "
                         f"pretrain_image_size {scale['pretrain_image_size']} in multiples of 8")
    step = int(scale["pretrain_alpha_iterations"]) + int(scale["pretrain_beta_iterations"])
    every = int(scale["resolution_tier_iterations"])
    tiers, parent = [], final_recipe
    for size in sizes:
        tiers.append(ResolutionTier(f"{final_recipe}_{size}px", size, parent, step, every))
        parent, step = tiers[-1].name, step + every
    return tiers


def available_subjects(subjects: dict, note=None) -> dict:
    """Subjects marked `optional: true` whose path matches no file are left out (with a note), e.g. a real clip that
    exists on one machine only."""
    kept = {}
    for name, spec in (subjects or {}).items():
        if spec.get("optional") and spec.get("path") and not glob.glob(spec["path"]):
            print(f"avatarlab: optional subject '{name}' skipped: nothing at {spec['path']}", file=note or sys.stderr)
            continue
        kept[name] = spec
    return kept


def check_input_names(subject: str, paths: list[str]) -> None:
    """A subject's input files must have names the workflow can carry: UTF-8 (Snakemake writes them into its
    locks) and without braces (Snakemake reads {...} in a path as a wildcard). Raises ValueError naming the file."""
    for path in paths:
        try:
            path.encode("utf-8")
        except UnicodeEncodeError:
            shown = path.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")
            raise ValueError(f"subject '{subject}': the file name {shown!r} is not UTF-8; rename the file") from None
        if "{" in path or "}" in path:
            raise ValueError(f"subject '{subject}': the file name {path!r} holds a brace, which Snakemake reads as a "
                             "wildcard; rename the file") from None


@dataclass(frozen=True)
class ResolutionTier:
    """The final recipe's model continued at a higher resolution (seed 002, section 2.4: "300 000 iterations for
    every resolution (128, 256, 512)"; section 4: the ablations at 128x128, the best combination then at 256x256
    and 512x512): `parent`'s weights (the previous tier) trained on at `size` for `iterations` more iterations with
    the final recipe's strategy, from the parent's last iteration `start`."""
    name: str
    size: int
    parent: str
    start: int
    iterations: int

    def overrides(self) -> tuple[str, ...]:
        """The Hydra overrides of its pretraining step (with the final recipe's strategy): a beta-style
        continuation of the parent from `start`, at this tier's image and feature-map size."""
        return (f"model.image_size={self.size}", f"model.feature_size={self.size // 8}",
                f"pretrain.alpha_iterations={self.start}", f"pretrain.beta_iterations={self.iterations}")


class Plan:
    def __init__(self, config: dict, sweep_dir: str | Path | None = None, scale: dict | None = None):
        """`scale`: the composed conf/scale section (resolution tiers and iteration budgets; none without it)."""
        self.scale = config["scale"]
        self.results, self.logs = results_root(self.scale), logs_root(self.scale)
        self.tree = ResultsTree(self.results)
        self.subjects = available_subjects(config.get("subjects", {}))
        self.real_images = config["real_images"]
        # videos the frame interpolator also learns from, whole (no experiment holds their frames out; nothing else
        # uses them): their frames are extracted, nothing more
        self.motion_videos = available_subjects(config.get("interp_motion_videos") or {})
        clash = sorted(set(self.motion_videos) & (set(self.subjects) | {self.real_images["name"]}))
        if clash:
            raise ValueError(f"workflow config 'interp_motion_videos': {clash[0]} is also a subject; name it apart")
        if self.real_images["name"] in self.subjects:
            raise ValueError(f"workflow config 'subjects': {self.real_images['name']!r} is the real image set's name "
                             "(real_images.name); name the subject apart")
        self.all_subjects = {**self.subjects, self.real_images["name"]: self.real_images, **self.motion_videos}
        for name in self.all_subjects:
            check_input_names(name, self.subject_inputs(name))
        self.synthetic = [n for n, s in self.subjects.items() if s["source"] == "synthetic"]
        self.image_sets = [n for n, s in self.all_subjects.items() if s["source"] in ("portraits", "images")]
        self.videos = [n for n in self.subjects if n not in self.image_sets]
        # the video subjects the shared steps (the frame interpolator, the control figures) read: `shared_subjects`
        # (null: every video subject), so a subject added later does not retrain or redraw them
        shared = config.get("shared_subjects")
        self.shared_videos = self.videos if shared is None else [n for n in self.videos if n in shared]
        self.alphas, self.betas, self.renderers = config["alphas"], config["betas"], config["renderers"]
        self.pretrained = self.alphas + [f"{b}_from_{a}" for b in self.betas for a in self.alphas]
        self.final_recipe = config["final_recipe"]
        self.tiers = resolution_tiers(self.final_recipe, scale or {})
        self.initialisations = self.pretrained + [t.name for t in self.tiers]
        self.control_figures = {name: spec for name, spec in (config.get("control_figures") or {}).items()
                                if all(m in self.pretrained for m in spec["models"])}
        self.ablation_subjects = [s for s in config.get("ablation_subjects", []) if s in self.subjects]
        # the workflow config's `seeds`, else the scale's (conf/scale/<scale>.yaml workflow_seeds)
        self.seeds = int(config.get("seeds") or (scale or {}).get("workflow_seeds") or 1)
        self.interp_subjects = [s for s in config.get("interp_subjects", []) if s in self.subjects]
        self.transfers = [(t["avatar"], t["source"]) for t in config.get("transfers", [])
                          if t["avatar"] in self.subjects and t["source"] in self.subjects]
        self.speech_models = sorted(p.stem for p in SPEECH_MODEL_DIR.glob("*.yaml"))
        self.speech_subjects = [s for s in config.get("speech_subjects", []) if s in self.subjects]
        self.speech_wav, self.speech_text = config.get("speech_wav"), config.get("speech_text", "bin blue at f two now")
        self.real_speech_clips = sorted({c for pattern in config.get("real_speech_clips") or []
                                         for c in glob.glob(pattern)})
        self.speech_audio_models = [m for m in self.speech_models if speech_model_kind(m) == "lstm"]  # audio in
        self.sweep_files = Path(sweep_dir) if sweep_dir else SWEEP_DIR
        self.sweeps = load_sweeps(self.sweep_files, config.get("sweep_seeds"))
        self.requested_sweeps = list(config.get("sweeps") or [])
        unknown = [s for s in self.requested_sweeps if s not in self.sweeps]
        if unknown:
            raise ValueError(f"workflow config 'sweeps': no conf/sweep/{unknown[0]}.yaml (there are: "
                             f"{', '.join(sorted(self.sweeps)) or 'none'})")

    # --- subjects -------------------------------------------------------------------------------------------------
    def subject_dir(self, subject: str) -> str:
        return self.tree.subject(subject)

    def subject_inputs(self, subject: str) -> list[str]:
        """Files the frames of a subject come from: its synthetic video, or the user's paths (globs allowed)."""
        spec = self.all_subjects[subject]
        if spec["source"] == "synthetic":
            return [self.tree.subject(subject, "input", "video.mp4")]
        if spec["source"] == "portraits":
            return [self.tree.subject(subject, "input", "images")]
        return sorted(glob.glob(spec["path"])) or [spec["path"]]

    def subject_truth(self, subject: str) -> list[str]:
        """The ground truth of a synthetic subject (an input of every step that reports errors against it)."""
        return [self.tree.subject(subject, "input", "truth.npz")] if subject in self.synthetic else []

    def subject_values(self, subject: str) -> dict:
        """Per-subject settings every preprocessing and avatar step gets (name, folder, truth, the subject's own
        `fps`, `max_frames` and `test_clips` from workflow/config.yaml)."""
        spec = self.all_subjects[subject]
        values = {"subject.name": subject, "preprocess.subject_dir": self.subject_dir(subject)}
        truth = self.subject_truth(subject)
        if truth:
            values["preprocess.truth"] = truth[0]
        if subject in self.image_sets:
            values["fit_rgb.mode"] = "images"
        else:  # the identity fit keeps out the frames its avatar is tested on
            values["fit_rgb.held_out.test_clips"] = self.test_clips(subject)
        for key, target, kind in (("fps", "preprocess.fps", float), ("max_frames", "preprocess.max_frames", int)):
            if spec.get(key) is not None:
                values[target] = kind(spec[key])
        return values

    #: Snakemake `priority` of a step's jobs (higher starts first among the ready ones). Every model waits for the
    #: chain pretraining image set -> alpha -> beta, so it goes first, then what the avatars wait for (the other
    #: subjects' preprocessing), then the long final-recipe fine-tunes, then the side chains (speech's corpus, models
    #: and real-clip scores, the interpolator; a job of up to 16 min at tiny that, left to the end, ran alone as the
    #: run's tail), then the base fine-tunes; figures, applications and scores (priority 0) fill the gaps. Without
    #: priorities a tiny run began with speech and the interpolator and started alpha pretraining after 45 minutes.
    #: A rule's priority does not pass to the jobs it waits for, so each of those carries its own: the tracking
    #: store's set-up (every training step needs it) first of all.
    PRIORITIES = {"init_tracking": 60, "pretraining_set": 50, "pretrain_alpha": 40, "pretrain_beta": 30,
                  "pretrain_resolution": 30, "subject_preprocessing": 20, "finetune_final": 15, "side_chain": 12,
                  "finetune": 10}
    #: the steps of a subject's preprocessing, from its images or synthetic video to its fit
    PREPROCESSING_STEPS = ("synthesize_portraits", "synthesize_subject", "extract_frames", "detect_landmarks",
                           "segment_masks", "fit_rgb")
    #: the steps of the side chains (speech's, the interpolator's): started after the final fine-tunes, not at the end
    SIDE_CHAIN_STEPS = ("speech_corpus", "speech_train", "speech_real_eval", "train_interpolator", "interpolate_frames")

    def step_priority(self, step: str, subject: str | None = None, recipe: str | None = None) -> int:
        """The priority of a job: `step` is the rule's name; `subject` (preprocessing) or `recipe` (fine-tuning)
        picks the job's place in the chain (see PRIORITIES)."""
        if step in self.PREPROCESSING_STEPS:
            if subject is None or subject == self.real_images["name"]:
                return self.PRIORITIES["pretraining_set"]
            return self.PRIORITIES["subject_preprocessing"]
        if step in self.SIDE_CHAIN_STEPS:
            return self.PRIORITIES["side_chain"]
        if step == "finetune_avatar":
            return self.PRIORITIES["finetune_final" if recipe == "final" else "finetune"]
        return self.PRIORITIES.get(step, 0)

    def real_set(self, name: str | None = None) -> dict:
        """The preprocessed image set pretraining reads (default: `real_images`): its fit, masks and frames."""
        name = name or self.real_images["name"]
        return {"fit": self.tree.subject(name, "fit_rgb.npz"), "masks": self.tree.subject(name, "masks.npz"),
                "frames": self.tree.subject(name, "frames.json")}

    def test_clips(self, subject: str) -> int:
        return int(self.all_subjects[subject].get("test_clips", 0))

    def finetune_values(self, key: AvatarKey, model: str) -> dict:
        """The config values naming an avatar (a fine-tuning or its evaluation): its subject (and the subject's own
        values), initialisation, frames variant, seed and folder (that of its model.pt)."""
        return {**self.subject_values(key.subject), "finetune.subject": key.subject,
                "finetune.subject_dir": self.subject_dir(key.subject), "finetune.init_name": key.init,
                "finetune.test_clips": self.test_clips(key.subject), "finetune.frames_variant": key.variant,
                "finetune.out_dir": str(Path(model).parent)}

    def interpolated_input(self, key: AvatarKey) -> list[str]:
        """What a fine-tuning reads beyond its subject's data: variant (c) trains on the interpolated frames too."""
        return [self.tree.subject(key.subject, "interpolated.npz")] if key.variant == "c" else []

    @staticmethod
    def finetune_choices(key: AvatarKey) -> tuple[str, ...]:
        """The config-group choices of a fine-tuning: its recipe and, for seed k > 0, the seed."""
        return (f"finetune={key.recipe}",) + ((f"seed={key.seed}",) if key.seed else ())

    def speech_audio(self) -> dict:
        """The audio the speech step animates: `speech_wav` (a path) if set, else `speech_text` spoken by espeak-ng."""
        return {"speech.wav": self.speech_wav} if self.speech_wav else {"speech.say": self.speech_text}

    # --- results --------------------------------------------------------------------------------------------------
    def avatar_dir(self, subject: str, recipe: str, init: str) -> str:
        return self.tree.avatar_of(AvatarKey(subject, recipe, init))

    def seeded(self, subject: str, recipe: str, init: str) -> list[str]:
        """The eval.json of an avatar's seeded repeats: seed 0 (the plain folder), seed 1, ..."""
        return [self.tree.avatar_of(key, "eval.json") for key in AvatarKey(subject, recipe, init).seeds(self.seeds)]

    def final_strategy(self) -> str:
        return self.final_recipe.split("_from_")[0]

    def tier(self, name: str) -> ResolutionTier:
        return next(t for t in self.tiers if t.name == name)

    def final_avatar(self, subject: str) -> str:
        """The avatar the applications use: the final recipe at the highest resolution the scale trains."""
        top = self.tiers[-1].name if self.tiers else self.final_recipe
        return self.tree.avatar(subject, "final", top, "model.pt")

    def preprocessing_outputs(self) -> list[str]:
        outputs = [self.tree.headmodel("render_grid.png"), self.tree.headmodel("dlib_check.json")]
        for subject in self.subjects:
            outputs += [self.tree.subject(subject, "fit_rgb.json"), self.tree.subject(subject, "interp.json")]
        outputs.append(self.tree.subject(self.real_images["name"], "fit_rgb.json"))  # the pretraining image set
        outputs += [self.tree.subject(s, "fit_rgbd.json") for s in self.synthetic]
        return outputs

    def pretrain_outputs(self) -> list[str]:
        return ([self.tree.pretrain(name, "eval.json") for name in self.initialisations]
                + [self.tree.report("renderer_experiment.json")]
                + [self.tree.controls(f"{name}.json") for name in self.control_figures])

    def avatar_outputs(self) -> list[str]:
        """Every subject's final-recipe avatar and its applications; the 14 base fine-tunes of the ablation subjects;
        the interpolation variants (base recipe; variant a is the plain base avatar of the same initialisation)."""
        outputs = []
        for subject in self.subjects:
            outputs += self.seeded(subject, "final", self.final_recipe)
            outputs += [self.tree.avatar(subject, "final", tier.name, "eval.json") for tier in self.tiers]
            outputs += [self.tree.app(subject, "novel_views.png"), self.tree.app(subject, "telepresence.json")]
        for subject in self.ablation_subjects:
            outputs += [self.tree.avatar(subject, "base", init, "eval.json") for init in self.pretrained]
            outputs += [path for init in self.alphas for path in self.seeded(subject, "base", init)]
        for subject in self.interp_subjects:
            outputs += [self.tree.avatar_of(AvatarKey(subject, "base", self.final_recipe, v), "eval.json")
                        for v in VARIANTS]
        outputs += [self.tree.app(a, f"reenact_{s}.mp4") for a, s in self.transfers]
        return sorted(set(outputs))

    def speech_outputs(self) -> list[str]:
        outputs = [self.tree.speech(m, "metrics.json") for m in self.speech_models]
        outputs += [self.tree.speech("real_eval.json")] if self.real_speech_clips else []
        return outputs + [self.tree.speech(f"speak_{s}.mp4") for s in self.speech_subjects]

    # --- sweeps ----------------------------------------------------------------------------------------------------
    def sweep_dir(self, name: str) -> str:
        return self.tree.sweep(name)

    def sweep_point(self, name: str, point: str):
        for p in self.sweeps[name].points:
            if p.name == point:
                return p
        raise ValueError(f"sweep {name}: no point {point}")

    def sweep_names(self, step: str) -> list[str]:
        """The sweeps of one kind of step (finetune, pretrain)."""
        return [n for n, s in self.sweeps.items() if s.step == step]

    def sweep_avatar(self, name: str) -> AvatarKey:
        """The avatar a fine-tuning sweep's points vary (its subject, recipe and initialisation)."""
        sweep = self.sweeps[name]
        return AvatarKey(sweep.subject, sweep.recipe, sweep.init)

    def sweep_tags(self, name: str, point: str) -> dict:
        """The MLflow tags of a sweep's point (values, not settings: a new tag reruns nothing)."""
        return {"tracking.sweep": name, "tracking.point": point,
                "tracking.point_overrides": " ".join(self.sweep_point(name, point).overrides)}

    def sweep_point_evals(self, name: str) -> list[str]:
        return [self.tree.sweep(name, p.name, "eval.json") for p in self.sweeps[name].points]

    def sweep_outputs(self, name: str) -> list[str]:
        return [self.tree.sweep(name, "table.md"), self.tree.sweep(name, "figure.png")]

    def report_inputs(self) -> list[str]:
        """The results the report reads: preprocessing, pretraining, avatars and speech."""
        return self.preprocessing_outputs() + self.pretrain_outputs() + self.avatar_outputs() + self.speech_outputs()

    def made_from(self, outputs: list[str]) -> list[str]:
        """The files the requested results are made from that a step could lose (a failed or killed step's outputs
        are deleted): trained models and the preprocessed data. Requested too, so that a missing one is made again
        and every result made from it is remade after it (Snakemake ignores a missing intermediate file whose
        descendants exist: snakemake/snakemake#1978)."""
        made = []
        for output in outputs:
            folder, _, name = output.rpartition("/")
            stage = self.tree.key(output).stage
            if name == "eval.json" and stage in ("pretrain", "avatars"):
                made += [f"{folder}/model.pt", f"{folder}/train.json"]
            elif name == "metrics.json" and stage == "speech":
                made += [f"{folder}/model.pt", self.tree.speech("corpus.npz")]
        for subject in [*self.subjects, self.real_images["name"]]:
            made += [self.tree.subject(subject, f) for f in ("frames.json", "landmarks.npz", "masks.npz",
                                                             "fit_rgb.npz")]
        made += [self.tree.subject(s, "frames.json") for s in self.motion_videos]
        made += [self.tree.interp("model.pt")] if self.subjects else []
        return sorted(set(made) - set(outputs))

    def final_outputs(self) -> list[str]:
        results = self.report_inputs()
        return (results + self.made_from(results) + [self.tree.report("README.md")]
                + [o for name in self.requested_sweeps for o in self.sweep_outputs(name)])
