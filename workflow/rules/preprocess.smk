# Per-subject preprocessing: frames -> landmarks -> masks -> FLAME fits (RGB, RGBD) and frame interpolation.


rule synthesize_subject:
    input:
        code=module_sources("avatarlab.data.synthetic_subject"),
    output:
        video=f"{RESULTS}/subjects/{{subject}}/input/video.mp4",
        truth=f"{RESULTS}/subjects/{{subject}}/input/truth.npz",
    log:
        f"{LOGS}/subjects/{{subject}}/synthesize.log",
    params:
        settings=lambda wc: settings("seed", "head_model", "render", "subject", modules=("avatarlab.data.synthetic_subject",)),
        hydra=lambda wc: hydra_args(f"{RESULTS}/subjects/{wc.subject}/.hydra/synthesize"),
        preset=lambda wc: SUBJECTS[wc.subject].get("preset", "talking"),
        seed=lambda wc: SUBJECTS[wc.subject].get("seed", 0),
    threads: step_threads("light")
    resources:
        **step_resources("light"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.data.synthetic_subject {params.hydra} threads={threads} subject.name={wildcards.subject}"
        " subject.preset={params.preset} subject.seed={params.seed} 'subject.video_out={output.video}'"
        " 'subject.truth_out={output.truth}' > {log} 2>&1"


rule extract_frames:
    input:
        media=subject_inputs,
        code=module_sources("avatarlab.preprocess.frames"),
    output:
        frames=directory(f"{RESULTS}/subjects/{{subject}}/frames"),
        meta=f"{RESULTS}/subjects/{{subject}}/frames.json",
    log:
        f"{LOGS}/subjects/{{subject}}/frames.log",
    params:
        settings=lambda wc: settings("preprocess", modules=("avatarlab.preprocess.frames",)),
        hydra=lambda wc: hydra_args(f"{RESULTS}/subjects/{wc.subject}/.hydra/frames"),
        subject=subject_args,
        inputs=lambda wc, input: "'preprocess.inputs=[" + ",".join(f'"{p}"' for p in input.media) + "]'",
    threads: step_threads("light")
    resources:
        **step_resources("light"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.preprocess.frames {params.hydra} threads={threads} {params.subject} {params.inputs}"
        " > {log} 2>&1"


rule detect_landmarks:
    input:
        meta=f"{RESULTS}/subjects/{{subject}}/frames.json",
        truth=lambda wc: subject_truth(wc.subject),
        code=module_sources("avatarlab.preprocess.track_landmarks"),
    output:
        points=f"{RESULTS}/subjects/{{subject}}/landmarks.npz",
        report=f"{RESULTS}/subjects/{{subject}}/landmarks.json",
    log:
        f"{LOGS}/subjects/{{subject}}/landmarks.log",
    params:
        settings=lambda wc: settings("preprocess", modules=("avatarlab.preprocess.track_landmarks",)),
        hydra=lambda wc: hydra_args(f"{RESULTS}/subjects/{wc.subject}/.hydra/landmarks"),
        subject=subject_args,
    threads: step_threads("light")
    resources:
        **step_resources("light"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.preprocess.track_landmarks {params.hydra} threads={threads} {params.subject} > {log} 2>&1"


rule segment_masks:
    input:
        points=f"{RESULTS}/subjects/{{subject}}/landmarks.npz",
        truth=lambda wc: subject_truth(wc.subject),
        code=module_sources("avatarlab.preprocess.masks"),
    output:
        masks=f"{RESULTS}/subjects/{{subject}}/masks.npz",
        report=f"{RESULTS}/subjects/{{subject}}/masks.json",
    log:
        f"{LOGS}/subjects/{{subject}}/masks.log",
    params:
        settings=lambda wc: settings("preprocess", modules=("avatarlab.preprocess.masks",)),
        hydra=lambda wc: hydra_args(f"{RESULTS}/subjects/{wc.subject}/.hydra/masks"),
        subject=subject_args,
    threads: step_threads("light")
    resources:
        **step_resources("light"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.preprocess.masks {params.hydra} threads={threads} {params.subject} > {log} 2>&1"


rule fit_rgb:
    input:
        points=f"{RESULTS}/subjects/{{subject}}/landmarks.npz",
        masks=f"{RESULTS}/subjects/{{subject}}/masks.npz",
        truth=lambda wc: subject_truth(wc.subject),
        code=module_sources("avatarlab.preprocess.fit_rgb"),
    output:
        params=f"{RESULTS}/subjects/{{subject}}/fit_rgb.npz",
        report=f"{RESULTS}/subjects/{{subject}}/fit_rgb.json",
        overlay=report(f"{RESULTS}/subjects/{{subject}}/fit_rgb_overlay.png", caption="../report/fit_rgb.rst",
                       category="Preprocessing", subcategory="{subject}"),
    log:
        f"{LOGS}/subjects/{{subject}}/fit_rgb.log",
    params:
        settings=lambda wc: settings("seed", "preprocess", "fit_rgb", "head_model", "render", modules=("avatarlab.preprocess.fit_rgb",)),
        hydra=lambda wc: hydra_args(f"{RESULTS}/subjects/{wc.subject}/.hydra/fit_rgb"),
        subject=subject_args,
    threads: step_threads("fit")
    resources:
        **step_resources("fit"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.preprocess.fit_rgb {params.hydra} threads={threads} {params.subject} > {log} 2>&1"


rule fit_rgbd:
    input:
        truth=f"{RESULTS}/subjects/{{subject}}/input/truth.npz",
        video=f"{RESULTS}/subjects/{{subject}}/input/video.mp4",
        rgb=f"{RESULTS}/subjects/{{subject}}/fit_rgb.json",
        code=module_sources("avatarlab.preprocess.fit_rgbd"),
    output:
        report=f"{RESULTS}/subjects/{{subject}}/fit_rgbd.json",
    log:
        f"{LOGS}/subjects/{{subject}}/fit_rgbd.log",
    params:
        settings=lambda wc: settings("seed", "preprocess", "fit_rgbd", "head_model", modules=("avatarlab.preprocess.fit_rgbd",)),
        hydra=lambda wc: hydra_args(f"{RESULTS}/subjects/{wc.subject}/.hydra/fit_rgbd"),
        subject=subject_args,
    threads: step_threads("fit")
    resources:
        **step_resources("fit"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.preprocess.fit_rgbd {params.hydra} threads={threads} {params.subject}"
        " 'fit_rgbd.out={output.report}' > {log} 2>&1"


rule interpolate_frames:
    input:
        meta=f"{RESULTS}/subjects/{{subject}}/frames.json",
        code=module_sources("avatarlab.preprocess.interp.run"),
    output:
        report=f"{RESULTS}/subjects/{{subject}}/interp.json",
        frames=f"{RESULTS}/subjects/{{subject}}/interpolated.npz",
        figure=report(f"{RESULTS}/subjects/{{subject}}/interp_comparison.png", caption="../report/interp.rst",
                      category="Preprocessing", subcategory="{subject}"),
    log:
        f"{LOGS}/subjects/{{subject}}/interp.log",
    params:
        settings=lambda wc: settings("seed", "preprocess", "interp", modules=("avatarlab.preprocess.interp.run",)),
        hydra=lambda wc: hydra_args(f"{RESULTS}/subjects/{wc.subject}/.hydra/interp"),
        subject=subject_args,
    threads: step_threads("fit")
    resources:
        **step_resources("fit"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.preprocess.interp.run {params.hydra} threads={threads} {params.subject} > {log} 2>&1"
