# Package the scene for the simulator (srfpipe.sim.package): manifest, fruit targets, meshes, MJCF.
# images.zarr is read for its ground truth only (apples.json on the orchard: count and centroid error).


rule package:
    input:
        occupancy=rules.distill.output[0],
        srf=rules.train.output[0],
        images=rules.downscale.output[0],
    output:
        directory(f"{RESULTS}/{{scene}}/sim"),
    params:
        options=scene_section("sim"),
    log:
        "logs/{scene}/package.log",
    benchmark:
        "benchmarks/runs/{scene}/package.tsv"
    threads: 2
    resources:
        mem_mb=4000,
        runtime=30,
    shell:
        "srfpipe package --occupancy {input.occupancy:q} --srf {input.srf:q} --images {input.images:q} "
        "--threads {threads} --options {params.options:q} --out {output:q} > {log:q} 2>&1"
