# The head model itself: a look at it, and a check that face tooling sees it as a face.


rule render_demo:
    input:
        code=module_sources("avatarlab.headmodel.render_demo"),
    output:
        grid=report(f"{RESULTS}/headmodel/render_grid.png", caption="../report/render_grid.rst",
                    category="Head model"),
    log:
        f"{LOGS}/headmodel/render_demo.log",
    params:
        settings=lambda wc: settings("seed", "head_model", "render", "demo", modules=("avatarlab.headmodel.render_demo",)),
        hydra=hydra_args(f"{RESULTS}/headmodel/.hydra/render_demo"),
    threads: step_threads("light")
    resources:
        **step_resources("light"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.headmodel.render_demo {params.hydra} threads={threads} 'demo.out={output.grid}' > {log} 2>&1"


rule dlib_check:
    input:
        code=module_sources("avatarlab.headmodel.dlib_check"),
    output:
        report=f"{RESULTS}/headmodel/dlib_check.json",
        overlay=report(f"{RESULTS}/headmodel/dlib_check_overlay.png", caption="../report/dlib_check.rst",
                       category="Head model"),
    log:
        f"{LOGS}/headmodel/dlib_check.log",
    params:
        settings=lambda wc: settings("seed", "head_model", "render", "dlib_check", modules=("avatarlab.headmodel.dlib_check",)),
        hydra=hydra_args(f"{RESULTS}/headmodel/.hydra/dlib_check"),
    threads: step_threads("light")
    resources:
        **step_resources("light"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.headmodel.dlib_check {params.hydra} threads={threads} 'dlib_check.out={output.report}'"
        " 'dlib_check.overlay={output.overlay}' > {log} 2>&1"
