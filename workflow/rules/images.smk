# Undistort and downscale the capture's images (OpenCV INTER_AREA), one image in memory at a time.


rule downscale:
    input:
        poses=rules.poses.output[0],
    output:
        directory(f"{RESULTS}/{{scene}}/images.zarr"),
    params:
        options=scene_section("images"),
    log:
        "logs/{scene}/downscale.log",
    benchmark:
        "benchmarks/runs/{scene}/downscale.tsv"
    threads: 1
    resources:
        mem_mb=4000,
        runtime=60,
    shell:
        "srfpipe downscale --poses {input.poses:q} --options {params.options:q} --out {output:q} > {log:q} 2>&1"
