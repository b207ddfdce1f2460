# The built-in procedural captures (nerfstudio format + ground truth), and pose import.
# Both generators (and a video's frames) write results/{scene}/capture: each rule is constrained to
# its format's scenes.


rule orchard_capture:
    output:
        directory(f"{RESULTS}/{{scene}}/capture"),
    wildcard_constraints:
        scene=scenes_of_format("orchard"),
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
        "srfpipe orchard --options {params.options:q} --out {output:q} > {log:q} 2>&1"


# A thin sapling in millimetres, few far views, dark backdrop (srfpipe/scenes/plant.py).
rule plant_capture:
    output:
        directory(f"{RESULTS}/{{scene}}/capture"),
    wildcard_constraints:
        scene=scenes_of_format("plant"),
    params:
        options=scene_section("plant"),
    log:
        "logs/{scene}/plant_capture.log",
    benchmark:
        "benchmarks/runs/{scene}/plant_capture.tsv"
    threads: 1
    resources:
        mem_mb=2000,
        runtime=10,
    shell:
        "srfpipe plant --options {params.options:q} --out {output:q} > {log:q} 2>&1"


# A video's frames (srfpipe/poses/video.py): the sharpest of equal windows, at most source.max_frames,
# written with their timestamps as results/{scene}/capture, which the poses rule poses by SfM.
rule video_frames:
    input:
        video=lambda wildcards: SCENES[wildcards.scene]["source"]["path"],
    output:
        directory(f"{RESULTS}/{{scene}}/capture"),
    wildcard_constraints:
        scene=scenes_of_format("video"),
    params:
        options=scene_section("source"),
    log:
        "logs/{scene}/video_frames.log",
    benchmark:
        "benchmarks/runs/{scene}/video_frames.tsv"
    threads: 1
    resources:
        mem_mb=2000,
        runtime=30,
    shell:
        "srfpipe frames --options {params.options:q} --video {input.video:q} --out {output:q} > {log:q} 2>&1"


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
        "srfpipe poses --source {params.source:q} --capture {input.capture:q} "
        "--options {params.options:q} --threads {threads} --out {output:q} > {log:q} 2>&1"
