# Speech-driven animation (seeds 000 and 001): corpus -> models (conf/speech_model) -> table rows -> audio -> avatar.


rule speech_corpus:
    output:
        corpus=TREE.speech("corpus.npz"),
        summary=TREE.speech("corpus.json"),
    log:
        LOG_TREE.speech("corpus.log"),
    params:
        **step_params("avatarlab.speech.corpus", values=lambda wc, input, output: {"speech.corpus": output.corpus},
                      run_dir=lambda wc: TREE.speech(".hydra", "corpus")),
    priority: PLAN.step_priority("speech_corpus")
    threads: step_threads("light")
    resources:
        **step_resources("light"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.runtime.forkserver avatarlab.speech.corpus {params.args} threads={threads} > {log} 2>&1"


rule speech_train:
    input:
        corpus=TREE.speech("corpus.npz"),
        tracking=TRACKING_READY,
    output:
        model=TREE.speech("{speech_model}", "model.pt"),
        metrics=TREE.speech("{speech_model}", "metrics.json"),
    log:
        LOG_TREE.speech("{speech_model}.log"),
    params:
        **step_params(
            "avatarlab.speech.train", extra=lambda wc: (f"speech_model={wc.speech_model}",),
            values=lambda wc, input, output: {"speech.corpus": input.corpus,
                                              "speech.out_dir": str(Path(output.model).parent)},
            run_dir=lambda wc: TREE.speech(".hydra", wc.speech_model)),
    priority: PLAN.step_priority("speech_train")
    threads: step_threads("speech")
    resources:
        **step_resources("speech"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.runtime.forkserver avatarlab.speech.train {params.args} threads={threads} > {log} 2>&1"


rule speak:
    input:
        speech=TREE.speech("lstm_reg", "model.pt"),
        avatar=lambda wc: PLAN.final_avatar(wc.subject),
        fit=TREE.subject("{subject}", "fit_rgb.npz"),
        wav=[config["speech_wav"]] if config.get("speech_wav") else [],
    output:
        video=report(TREE.speech("speak_{subject}.mp4"), caption="../report/speak.rst", category="Speech"),
        strip=TREE.speech("speak_{subject}.png"),
        meta=TREE.speech("speak_{subject}.json"),
    log:
        LOG_TREE.speech("speak_{subject}.log"),
    params:
        **step_params("avatarlab.speech.animate", values=lambda wc, input, output: {
            **PLAN.subject_values(wc.subject), "apps.subject_dir": PLAN.subject_dir(wc.subject), **PLAN.speech_audio(),
            "speech.animate_model": input.speech, "apps.avatar": input.avatar, "apps.out": output.video},
            run_dir=lambda wc: TREE.speech(".hydra", f"speak_{wc.subject}")),
        audio=lambda wc: PLAN.speech_audio(),
    threads: step_threads("light")
    resources:
        **step_resources("light"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.runtime.forkserver avatarlab.speech.animate {params.args} threads={threads} > {log} 2>&1"


rule speech_real_eval:
    """The seed-000 audio models (trained on the synthetic corpus, then fine-tuned on the real clips with the scored
    clip or speaker left out) on real GRID and Obama clips, beside a still mouth, where the clips exist."""
    input:
        models=[TREE.speech(m, "model.pt") for m in PLAN.speech_audio_models],
        clips=PLAN.real_speech_clips,
    output:
        report=TREE.speech("real_eval.json"),
    log:
        LOG_TREE.speech("real_eval.log"),
    params:
        **step_params("avatarlab.speech.real_eval", values=lambda wc, input, output: {
            "speech.real_clips": list(input.clips), "speech.real_models": list(input.models),
            "speech.real_eval_out": output.report},
            run_dir=lambda wc: TREE.speech(".hydra", "real_eval")),
    priority: PLAN.step_priority("speech_real_eval")
    threads: step_threads("light")
    resources:
        **step_resources("light"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.runtime.forkserver avatarlab.speech.real_eval {params.args} threads={threads} > {log} 2>&1"


rule speech_all:
    input:
        PLAN.speech_outputs(),
