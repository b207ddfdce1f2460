# The built-in procedural orchard capture (nerfstudio format + ground truth), and pose import.


rule orchard_capture:
    output:
        directory(f"{RESULTS}/{{scene}}/capture"),
    params:
        options=scene_section("orchard"),
    log:
        "logs/{scene}/orchard_capture.log",
    benchmark:
        "benchmarks/runs/{scene}/orchard_capture.tsv"
    threads: 2
    resources:
        mem_mb=4000,
        runtime=30,
    shell:
        "srfpipe orchard --options {params.options:q} --out {output} > {log} 2>&1"


rule poses:
    input:
        capture=capture_dir,
    output:
        directory(f"{RESULTS}/{{scene}}/poses.zarr"),
    params:
        source=scene_section("source"),
        options=scene_section("poses"),
    log:
        "logs/{scene}/poses.log",
    benchmark:
        "benchmarks/runs/{scene}/poses.tsv"
    threads: 2
    resources:
        mem_mb=8000,
        runtime=120,
    shell:
        "srfpipe poses --source {params.source:q} --capture {input.capture} "
        "--options {params.options:q} --threads {threads} --out {output} > {log} 2>&1"
