# Distill the trained field into the occupancy cache the simulator queries (srfpipe.occupancy).


rule distill:
    input:
        srf=f"{RESULTS}/{{scene}}/srf.zarr",
    output:
        directory(f"{RESULTS}/{{scene}}/occupancy.zarr"),
    params:
        options=scene_section("occupancy"),
    log:
        "logs/{scene}/distill.log",
    benchmark:
        "benchmarks/runs/{scene}/distill.tsv"
    threads: 2
    resources:
        mem_mb=8000,
        runtime=60,
    shell:
        "srfpipe distill --srf {input.srf:q} --options {params.options:q} "
        "--out {output:q} > {log:q} 2>&1"
