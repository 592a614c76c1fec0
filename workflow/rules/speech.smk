# Speech-driven animation (seeds 000 and 001): corpus -> models -> table rows -> audio -> avatar video.


rule speech_corpus:
    input:
        code=module_sources("avatarlab.speech.corpus"),
    output:
        corpus=f"{RESULTS}/speech/corpus.npz",
        summary=f"{RESULTS}/speech/corpus.json",
    log:
        f"{LOGS}/speech/corpus.log",
    params:
        settings=lambda wc: settings("seed", "head_model", "speech", modules=("avatarlab.speech.corpus",)),
        hydra=lambda wc: hydra_args(f"{RESULTS}/speech/.hydra/corpus"),
    threads: step_threads("light")
    resources:
        **step_resources("light"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.speech.corpus {params.hydra} threads={threads} 'speech.corpus={output.corpus}' > {log} 2>&1"


rule speech_train:
    input:
        corpus=f"{RESULTS}/speech/corpus.npz",
        tracking=TRACKING_READY,
        code=module_sources("avatarlab.speech.train"),
    output:
        model=f"{RESULTS}/speech/{{speech_model}}/model.pt",
        metrics=f"{RESULTS}/speech/{{speech_model}}/metrics.json",
    log:
        f"{LOGS}/speech/{{speech_model}}.log",
    params:
        settings=lambda wc: settings("seed", "head_model", "speech", "tracking", modules=("avatarlab.speech.train",)),
        hydra=lambda wc: hydra_args(f"{RESULTS}/speech/.hydra/{wc.speech_model}"),
        run=lambda wc: " ".join(f"'{a}'" for a in SPEECH_MODELS[wc.speech_model]),
        out_dir=lambda wc: f"{RESULTS}/speech/{wc.speech_model}",
    threads: step_threads("speech")
    resources:
        **step_resources("speech"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.speech.train {params.hydra} threads={threads} {params.run} 'speech.corpus={input.corpus}'"
        " 'speech.out_dir={params.out_dir}' > {log} 2>&1"


rule speak:
    input:
        speech=f"{RESULTS}/speech/lstm_reg/model.pt",
        avatar=lambda wc: final_avatar(wc.subject),
        fit=f"{RESULTS}/subjects/{{subject}}/fit_rgb.npz",
        wav=[config["speech_wav"]] if config.get("speech_wav") else [],
        code=module_sources("avatarlab.speech.animate"),
    output:
        video=report(f"{RESULTS}/speech/speak_{{subject}}.mp4", caption="../report/speak.rst", category="Speech"),
        strip=f"{RESULTS}/speech/speak_{{subject}}.png",
        meta=f"{RESULTS}/speech/speak_{{subject}}.json",
    log:
        f"{LOGS}/speech/speak_{{subject}}.log",
    params:
        settings=lambda wc: settings("speech", "apps", modules=("avatarlab.speech.animate",)),
        hydra=lambda wc: hydra_args(f"{RESULTS}/speech/.hydra/speak_{wc.subject}"),
        subject=subject_args,
        audio=lambda wc: speech_input_args(),
    threads: step_threads("light")
    resources:
        **step_resources("light"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.speech.animate {params.hydra} threads={threads} {params.subject} {params.audio}"
        " 'speech.animate_model={input.speech}' 'apps.avatar={input.avatar}' 'apps.out={output.video}' > {log} 2>&1"


rule speech_grid_eval:
    """The seed-000 model (trained on the synthetic corpus) tested on real GRID clips, where they exist."""
    input:
        speech=f"{RESULTS}/speech/lstm_reg/model.pt",
        clips=GRID_CLIPS,
        code=module_sources("avatarlab.speech.grid"),
    output:
        report=f"{RESULTS}/speech/grid_eval.json",
    log:
        f"{LOGS}/speech/grid_eval.log",
    params:
        settings=lambda wc: settings("speech", modules=("avatarlab.speech.grid",)),
        hydra=lambda wc: hydra_args(f"{RESULTS}/speech/.hydra/grid_eval"),
        clips=config.get("grid_clips"),
    threads: step_threads("light")
    resources:
        **step_resources("light"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.speech.grid {params.hydra} threads={threads} 'speech.grid_clips={params.clips}'"
        " 'speech.animate_model={input.speech}' 'apps.out={output.report}' > {log} 2>&1"


rule speech_all:
    input:
        speech_outputs(),
