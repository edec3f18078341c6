# lfstudy: the parametric light-field PIV study.
#   snakemake --cores all --configfile config/demo.yaml
from lfstudy.config import expand_cases, validate_config

configfile: "config/demo.yaml"

CFG = validate_config(config)           # one clear error on a bad config, defaults filled
NAME = CFG["name"]
CASES = [c.case_id for c in expand_cases(CFG)]
OUT = f"results/{NAME}"

wildcard_constraints:
    case="mag~[^/]+/fnum~[^/]+/pitch~[^/]+/ppp~[^/]+/flow~[^/]+",


rule all:
    input:
        expand(f"{OUT}/{{case}}/camera.json", case=CASES),


rule camera:
    output:
        json=f"{OUT}/{{case}}/camera.json",
        planes=directory(f"{OUT}/{{case}}/focal_planes.zarr"),
    log:
        f"{OUT}/logs/camera/{{case}}.log",
    benchmark:
        f"{OUT}/benchmarks/camera/{{case}}.tsv"
    threads: 1
    run:
        from lfstudy.workflow import run_optics, set_threads
        set_threads(threads)
        run_optics(CFG, wildcards.case, output.json, output.planes)
