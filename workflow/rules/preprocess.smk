# Per-subject preprocessing: frames -> landmarks -> masks -> FLAME fits (RGB, RGBD) and frame interpolation.


rule synthesize_subject:
    output:
        video=TREE.subject("{subject}", "input", "video.mp4"),
        truth=TREE.subject("{subject}", "input", "truth.npz"),
    log:
        LOG_TREE.subject("{subject}", "synthesize.log"),
    params:
        **step_params(
            "avatarlab.preprocess.synthetic_subject",
            values=lambda wc, input, output: {
                "subject.name": wc.subject, "subject.preset": PLAN.all_subjects[wc.subject].get("preset", "talking"),
                "subject.seed": int(PLAN.all_subjects[wc.subject].get("seed", 0)), "subject.video_out": output.video,
                "subject.truth_out": output.truth},
            run_dir=lambda wc: TREE.subject(wc.subject, ".hydra", "synthesize")),
    priority: lambda wc: PLAN.step_priority("synthesize_subject", wc.subject)
    threads: step_threads("light")
    resources:
        **step_resources("light"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.runtime.forkserver avatarlab.preprocess.synthetic_subject {params.args} threads={threads} > {log} 2>&1"


rule extract_frames:
    input:
        media=lambda wc: PLAN.subject_inputs(wc.subject),
    output:
        frames=directory(TREE.subject("{subject}", "frames")),
        meta=TREE.subject("{subject}", "frames.json"),
    log:
        LOG_TREE.subject("{subject}", "frames.log"),
    params:
        **subject_step("avatarlab.preprocess.frames", "frames", **{"preprocess.inputs": lambda i, o: list(i.media)}),
    priority: lambda wc: PLAN.step_priority("extract_frames", wc.subject)
    threads: step_threads("light")
    resources:
        **step_resources("light"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.runtime.forkserver avatarlab.preprocess.frames {params.args} threads={threads} > {log} 2>&1"


rule detect_landmarks:
    input:
        meta=TREE.subject("{subject}", "frames.json"),
        truth=lambda wc: PLAN.subject_truth(wc.subject),
    output:
        points=TREE.subject("{subject}", "landmarks.npz"),
        report=TREE.subject("{subject}", "landmarks.json"),
    log:
        LOG_TREE.subject("{subject}", "landmarks.log"),
    params:
        **subject_step("avatarlab.preprocess.track_landmarks", "landmarks"),
    priority: lambda wc: PLAN.step_priority("detect_landmarks", wc.subject)
    threads: step_threads("light")
    resources:
        **step_resources("light"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.runtime.forkserver avatarlab.preprocess.track_landmarks {params.args} threads={threads} > {log} 2>&1"


rule segment_masks:
    input:
        points=TREE.subject("{subject}", "landmarks.npz"),
        truth=lambda wc: PLAN.subject_truth(wc.subject),
    output:
        masks=TREE.subject("{subject}", "masks.npz"),
        report=TREE.subject("{subject}", "masks.json"),
    log:
        LOG_TREE.subject("{subject}", "masks.log"),
    params:
        **subject_step("avatarlab.preprocess.masks", "masks"),
    priority: lambda wc: PLAN.step_priority("segment_masks", wc.subject)
    threads: step_threads("light")
    resources:
        **step_resources("light"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.runtime.forkserver avatarlab.preprocess.masks {params.args} threads={threads} > {log} 2>&1"


rule fit_rgb:
    input:
        points=TREE.subject("{subject}", "landmarks.npz"),
        masks=TREE.subject("{subject}", "masks.npz"),
        truth=lambda wc: PLAN.subject_truth(wc.subject),
    output:
        params=TREE.subject("{subject}", "fit_rgb.npz"),
        report=TREE.subject("{subject}", "fit_rgb.json"),
        overlay=report(TREE.subject("{subject}", "fit_rgb_overlay.png"), caption="../report/fit_rgb.rst",
                       category="Preprocessing", subcategory="{subject}"),
    log:
        LOG_TREE.subject("{subject}", "fit_rgb.log"),
    params:
        **subject_step("avatarlab.preprocess.fit_rgb", "fit_rgb"),
    priority: lambda wc: PLAN.step_priority("fit_rgb", wc.subject)
    threads: step_threads("fit")
    resources:
        **step_resources("fit"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.runtime.forkserver avatarlab.preprocess.fit_rgb {params.args} threads={threads} > {log} 2>&1"


rule fit_rgbd:
    input:
        truth=TREE.subject("{subject}", "input", "truth.npz"),
        video=TREE.subject("{subject}", "input", "video.mp4"),
        rgb=TREE.subject("{subject}", "fit_rgb.json"),
    output:
        report=TREE.subject("{subject}", "fit_rgbd.json"),
    log:
        LOG_TREE.subject("{subject}", "fit_rgbd.log"),
    params:
        **subject_step("avatarlab.preprocess.fit_rgbd", "fit_rgbd", **{
            "fit_rgbd.out": lambda i, o: o.report, "fit_rgbd.video": lambda i, o: i.video,
            "fit_rgbd.rgb_report": lambda i, o: i.rgb}),
    threads: step_threads("fit")
    resources:
        **step_resources("fit"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.runtime.forkserver avatarlab.preprocess.fit_rgbd {params.args} threads={threads} > {log} 2>&1"


rule train_interpolator:
    """The XVFI-style frame interpolator, trained once on the shared subjects' videos (interp.strides) and the motion
    videos (whole), then used for each subject; the frames the interpolation experiment holds out are never among
    its training frames."""
    input:
        meta=[TREE.subject(s, "frames.json") for s in PLAN.shared_videos],
        motion=[TREE.subject(s, "frames.json") for s in PLAN.motion_videos],
    output:
        model=TREE.interp("model.pt"),
        report=TREE.interp("train.json"),
    log:
        LOG_TREE.interp("train.log"),
    params:
        **step_params("avatarlab.preprocess.interp.pretrain", values=lambda wc, input, output: {
            "interp.subject_dirs": [str(Path(m).parent) for m in input.meta],
            "interp.motion_dirs": [str(Path(m).parent) for m in input.motion],
            "interp.out_dir": str(Path(output.model).parent)},
            run_dir=lambda wc: TREE.interp(".hydra")),
    priority: PLAN.step_priority("train_interpolator")
    threads: step_threads("fit")
    resources:
        **step_resources("fit"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.runtime.forkserver avatarlab.preprocess.interp.pretrain {params.args} threads={threads} > {log} 2>&1"


rule interpolate_frames:
    input:
        meta=TREE.subject("{subject}", "frames.json"),
        model=TREE.interp("model.pt"),
    output:
        report=TREE.subject("{subject}", "interp.json"),
        frames=TREE.subject("{subject}", "interpolated.npz"),
        figure=report(TREE.subject("{subject}", "interp_comparison.png"), caption="../report/interp.rst",
                      category="Preprocessing", subcategory="{subject}"),
    log:
        LOG_TREE.subject("{subject}", "interp.log"),
    params:
        **subject_step("avatarlab.preprocess.interp.run", "interp", **{"interp.model": lambda i, o: i.model}),
    priority: PLAN.step_priority("interpolate_frames")
    threads: step_threads("fit")
    resources:
        **step_resources("fit"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.runtime.forkserver avatarlab.preprocess.interp.run {params.args} threads={threads} > {log} 2>&1"
