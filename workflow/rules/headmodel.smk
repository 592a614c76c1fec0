# The head model itself: a look at it, and a check that face tooling sees it as a face.


rule render_demo:
    output:
        grid=report(TREE.headmodel("render_grid.png"), caption="../report/render_grid.rst",
                    category="Head model"),
    log:
        LOG_TREE.headmodel("render_demo.log"),
    params:
        **step_params("avatarlab.pretrain.head_model_demo", values=lambda wc, input, output: {"demo.out": output.grid},
                      run_dir=lambda wc: TREE.headmodel(".hydra", "render_demo")),
    threads: step_threads("light")
    resources:
        **step_resources("light"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.runtime.forkserver avatarlab.pretrain.head_model_demo {params.args} threads={threads} > {log} 2>&1"


rule dlib_check:
    output:
        report=TREE.headmodel("dlib_check.json"),
        overlay=report(TREE.headmodel("dlib_check_overlay.png"), caption="../report/dlib_check.rst",
                       category="Head model"),
    log:
        LOG_TREE.headmodel("dlib_check.log"),
    params:
        **step_params("avatarlab.pretrain.dlib_check",
                      values=lambda wc, input, output: {"dlib_check.out": output.report,
                                                        "dlib_check.overlay": output.overlay},
                      run_dir=lambda wc: TREE.headmodel(".hydra", "dlib_check")),
    threads: step_threads("light")
    resources:
        **step_resources("light"),
    conda:
        "../envs/avatarlab.yaml"
    shell:
        "python -m avatarlab.runtime.forkserver avatarlab.pretrain.dlib_check {params.args} threads={threads} > {log} 2>&1"
