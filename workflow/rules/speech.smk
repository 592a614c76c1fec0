# Speech-driven animation (seeds 000 and 001): corpus -> models (conf/speech_model) -> table rows -> audio -> avatar.


rule speech_corpus:
    output:
        corpus=f"{RESULTS}/speech/corpus.npz",
        summary=f"{RESULTS}/speech/corpus.json",
    log:
        f"{LOGS}/speech/corpus.log",
    params:
        **step_params("avatarlab.speech.corpus", values=lambda wc, input, output: {"speech.corpus": output.corpus},
                      run_dir=lambda wc: f"{RESULTS}/speech/.hydra/corpus"),
    threads: step_threads("light")
    resources:
        **step_resources("light"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.speech.corpus {params.args} threads={threads} > {log} 2>&1"


rule speech_train:
    input:
        corpus=f"{RESULTS}/speech/corpus.npz",
        tracking=TRACKING_READY,
    output:
        model=f"{RESULTS}/speech/{{speech_model}}/model.pt",
        metrics=f"{RESULTS}/speech/{{speech_model}}/metrics.json",
    log:
        f"{LOGS}/speech/{{speech_model}}.log",
    params:
        **step_params(
            "avatarlab.speech.train", extra=lambda wc: (f"speech_model={wc.speech_model}",),
            values=lambda wc, input, output: {"speech.corpus": input.corpus,
                                              "speech.out_dir": str(Path(output.model).parent)},
            run_dir=lambda wc: f"{RESULTS}/speech/.hydra/{wc.speech_model}"),
    threads: step_threads("speech")
    resources:
        **step_resources("speech"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.speech.train {params.args} threads={threads} > {log} 2>&1"


rule speak:
    input:
        speech=f"{RESULTS}/speech/lstm_reg/model.pt",
        avatar=lambda wc: PLAN.final_avatar(wc.subject),
        fit=f"{RESULTS}/subjects/{{subject}}/fit_rgb.npz",
        wav=[config["speech_wav"]] if config.get("speech_wav") else [],
    output:
        video=report(f"{RESULTS}/speech/speak_{{subject}}.mp4", caption="../report/speak.rst", category="Speech"),
        strip=f"{RESULTS}/speech/speak_{{subject}}.png",
        meta=f"{RESULTS}/speech/speak_{{subject}}.json",
    log:
        f"{LOGS}/speech/speak_{{subject}}.log",
    params:
        **step_params("avatarlab.speech.animate", values=lambda wc, input, output: {
            **PLAN.subject_values(wc.subject), "apps.subject_dir": PLAN.subject_dir(wc.subject), **speech_audio(),
            "speech.animate_model": input.speech, "apps.avatar": input.avatar, "apps.out": output.video},
            run_dir=lambda wc: f"{RESULTS}/speech/.hydra/speak_{wc.subject}"),
        audio=lambda wc: speech_audio(),
    threads: step_threads("light")
    resources:
        **step_resources("light"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.speech.animate {params.args} threads={threads} > {log} 2>&1"


rule speech_grid_eval:
    """The seed-000 model (trained on the synthetic corpus) tested on real GRID clips, where they exist."""
    input:
        speech=f"{RESULTS}/speech/lstm_reg/model.pt",
        clips=PLAN.grid_clips,
    output:
        report=f"{RESULTS}/speech/grid_eval.json",
    log:
        f"{LOGS}/speech/grid_eval.log",
    params:
        **step_params("avatarlab.speech.grid", values=lambda wc, input, output: {
            "speech.grid_clips": list(input.clips), "speech.animate_model": input.speech, "apps.out": output.report},
            run_dir=lambda wc: f"{RESULTS}/speech/.hydra/grid_eval"),
    threads: step_threads("light")
    resources:
        **step_resources("light"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.speech.grid {params.args} threads={threads} > {log} 2>&1"


rule speech_all:
    input:
        PLAN.speech_outputs(),
