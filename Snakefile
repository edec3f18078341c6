# lfstudy: the parametric light-field PIV study.
#
#   snakemake --cores all --configfile config/demo.yaml
#
# Per case (results/<name>/<case id>/): camera -> particles -> displace ->
# simulate (a, b) -> register -> refocus -> reconstruct -> piv -> errors.
# The pinhole image and lenslet calibration are shared by all cases with the
# same magnification and lenslet pitch (results/<name>/calib/...). The study
# combines every case into study.zarr / study.csv and report.html.
# Rule bodies live in lfstudy/workflow.py. Per-case rules are shell commands
# (python -m lfstudy.workflow STAGE ...): far cheaper to start than a run:
# block, which Snakemake executes by spawning a whole new Snakemake. Each gets
# the config sections its stage reads as params, so editing the config reruns
# exactly the stages that depend on the change.
import json
import os
import sys

from snakemake.exceptions import WorkflowError

from lfstudy.config import expand_cases, validate_config
from lfstudy.study.case import calib_id
from lfstudy.workflow import logged, stage_config

configfile: "config/demo.yaml"

CFG = validate_config(config)           # one clear error on a bad config, defaults filled
NAME = CFG["name"]
CASES = [c.case_id for c in expand_cases(CFG)]
CASE_OF_CALIB = {}
for _c in CASES:
    CASE_OF_CALIB.setdefault(calib_id(_c), _c)
OUT = f"results/{NAME}"
LOG = f"{OUT}/logs"
BENCH = f"{OUT}/benchmarks"
# threads of the multi-threaded rules: all cores unless the config caps them
try:
    CORES = workflow.cores
except WorkflowError:  # no --cores: 'snakemake --report', --lint; no job runs
    CORES = 1
HEAVY = min(CORES, CFG["workflow"]["threads_per_job"] or CORES)

wildcard_constraints:
    case=r"mag~[^/]+/fnum~[^/]+/pitch~[^/]+/ppp~[^/]+/flow~[^/]+",
    calib=r"mag~[^/]+/pitch~[^/]+",
    frame=r"[ab]",


# Jobs run 'python' from PATH: put this interpreter's directory first, so a
# venv's snakemake works without activating the venv. (Not the interpreter's
# path in the command itself: Snakemake would see changed code, and rerun
# everything, whenever it is started through another path or symlink.)
os.environ["PATH"] = os.path.dirname(sys.executable) + os.pathsep + os.environ.get("PATH", "")
STAGE = "python -m lfstudy.workflow --config {params.cfg:q} --log {log:q} --threads {threads}"


# study and report read the whole config: they rerun on any change to it
STUDY_CFG = json.dumps(CFG, sort_keys=True, default=str)


def stage_params(stage, calib=False):
    """params.cfg of a per-case rule: the stage's config sections as JSON."""
    def cfg(wildcards):
        case = CASE_OF_CALIB[wildcards.calib] if calib else wildcards.case
        return json.dumps(stage_config(CFG, case, stage), sort_keys=True)
    return cfg


def centers_of(wildcards):
    """The shared calibration of a case (same magnification and pitch)."""
    return f"{OUT}/calib/{calib_id(wildcards.case)}/centers.zarr"


localrules: all


# Every intermediate is a target too: Snakemake (>= 7.7) ignores a deleted
# intermediate whose downstream outputs exist, but regenerates a missing
# target, and the newer file then reruns exactly what depends on it.
PER_CASE = ["camera.json", "focal_planes.zarr", "particles_a.zarr", "particles_b.zarr",
            "raw_a.zarr", "raw_b.zarr", "raw_a.tif", "raw_b.tif", "lightfield_a.zarr",
            "lightfield_b.zarr", "stack_a.zarr", "stack_b.zarr", "volume_a.zarr", "volume_b.zarr",
            "piv.zarr", "errors.zarr"]
PER_CALIB = ["pinhole.zarr", "pinhole.tif", "centers.zarr"]


rule all:
    input:
        f"{OUT}/study.zarr",
        f"{OUT}/study.csv",
        f"{OUT}/report.html",
        expand(f"{OUT}/{{case}}/{{name}}", case=CASES, name=PER_CASE),
        expand(f"{OUT}/calib/{{calib}}/{{name}}", calib=sorted(CASE_OF_CALIB), name=PER_CALIB),


rule camera:
    output:
        json=f"{OUT}/{{case}}/camera.json",
        planes=directory(f"{OUT}/{{case}}/focal_planes.zarr"),
    log: f"{LOG}/camera/{{case}}.log"
    benchmark: f"{BENCH}/camera/{{case}}.tsv"
    threads: 1
    params: cfg=stage_params("camera")
    shell: STAGE + " camera {output.json:q} {output.planes:q}"


rule particles:
    input: rules.camera.output.json
    output: directory(f"{OUT}/{{case}}/particles_a.zarr")
    log: f"{LOG}/particles/{{case}}.log"
    benchmark: f"{BENCH}/particles/{{case}}.tsv"
    threads: 1
    params: cfg=stage_params("particles")
    shell: STAGE + " particles {output[0]:q}"


rule displace:
    input: f"{OUT}/{{case}}/particles_a.zarr"
    output: directory(f"{OUT}/{{case}}/particles_b.zarr")
    log: f"{LOG}/displace/{{case}}.log"
    benchmark: f"{BENCH}/displace/{{case}}.tsv"
    threads: 1
    params: cfg=stage_params("displace")
    shell: STAGE + " displace {input[0]:q} {output[0]:q}"


rule simulate:
    input: f"{OUT}/{{case}}/particles_{{frame}}.zarr"
    output:
        zarr=directory(f"{OUT}/{{case}}/raw_{{frame}}.zarr"),
        tiff=f"{OUT}/{{case}}/raw_{{frame}}.tif",
    log: f"{LOG}/simulate/{{case}}_{{frame}}.log"
    benchmark: f"{BENCH}/simulate/{{case}}_{{frame}}.tsv"
    threads: HEAVY
    params: cfg=stage_params("simulate")
    shell: STAGE + " simulate {wildcards.frame} {input[0]:q} {output.zarr:q} {output.tiff:q}"


rule pinhole:
    output:
        zarr=directory(f"{OUT}/calib/{{calib}}/pinhole.zarr"),
        tiff=f"{OUT}/calib/{{calib}}/pinhole.tif",
    log: f"{LOG}/pinhole/{{calib}}.log"
    benchmark: f"{BENCH}/pinhole/{{calib}}.tsv"
    threads: HEAVY
    params: cfg=stage_params("pinhole", calib=True)
    shell: STAGE + " pinhole {output.zarr:q} {output.tiff:q}"


rule calibrate:
    input: f"{OUT}/calib/{{calib}}/pinhole.zarr"
    output: directory(f"{OUT}/calib/{{calib}}/centers.zarr")
    log: f"{LOG}/calibrate/{{calib}}.log"
    benchmark: f"{BENCH}/calibrate/{{calib}}.tsv"
    threads: HEAVY
    params: cfg=stage_params("calibrate", calib=True)
    shell: STAGE + " calibrate {input[0]:q} {output[0]:q}"


rule register:
    input:
        raw=f"{OUT}/{{case}}/raw_{{frame}}.zarr",
        centers=centers_of,
    output: directory(f"{OUT}/{{case}}/lightfield_{{frame}}.zarr")
    log: f"{LOG}/register/{{case}}_{{frame}}.log"
    benchmark: f"{BENCH}/register/{{case}}_{{frame}}.tsv"
    threads: 1
    params: cfg=stage_params("register")
    shell: STAGE + " register {input.raw:q} {input.centers:q} {output[0]:q}"


rule refocus:
    input: f"{OUT}/{{case}}/lightfield_{{frame}}.zarr"
    output: directory(f"{OUT}/{{case}}/stack_{{frame}}.zarr")
    log: f"{LOG}/refocus/{{case}}_{{frame}}.log"
    benchmark: f"{BENCH}/refocus/{{case}}_{{frame}}.tsv"
    threads: HEAVY
    params: cfg=stage_params("refocus")
    shell: STAGE + " refocus {input[0]:q} {output[0]:q}"


rule reconstruct:
    input:
        stack=f"{OUT}/{{case}}/stack_{{frame}}.zarr",
        lightfield=f"{OUT}/{{case}}/lightfield_{{frame}}.zarr",
        centers=centers_of,
    output: directory(f"{OUT}/{{case}}/volume_{{frame}}.zarr")
    log: f"{LOG}/reconstruct/{{case}}_{{frame}}.log"
    benchmark: f"{BENCH}/reconstruct/{{case}}_{{frame}}.tsv"
    threads: HEAVY
    params: cfg=stage_params("reconstruct")
    shell: STAGE + " reconstruct {input.stack:q} {input.lightfield:q} {input.centers:q} {output[0]:q}"


rule piv:
    input:
        a=f"{OUT}/{{case}}/volume_a.zarr",
        b=f"{OUT}/{{case}}/volume_b.zarr",
    output: directory(f"{OUT}/{{case}}/piv.zarr")
    log: f"{LOG}/piv/{{case}}.log"
    benchmark: f"{BENCH}/piv/{{case}}.tsv"
    threads: HEAVY
    params: cfg=stage_params("piv")
    shell: STAGE + " piv {input.a:q} {input.b:q} {output[0]:q}"


rule errors:
    input:
        piv=f"{OUT}/{{case}}/piv.zarr",
        volume=f"{OUT}/{{case}}/volume_a.zarr",
        particles=f"{OUT}/{{case}}/particles_a.zarr",
    output: directory(f"{OUT}/{{case}}/errors.zarr")
    log: f"{LOG}/errors/{{case}}.log"
    benchmark: f"{BENCH}/errors/{{case}}.tsv"
    threads: 1
    params: cfg=stage_params("errors")
    shell: STAGE + " errors {input.piv:q} {input.volume:q} {input.particles:q} {output[0]:q}"


rule study:
    input: expand(f"{OUT}/{{case}}/errors.zarr", case=CASES)
    output:
        zarr=directory(f"{OUT}/study.zarr"),
        csv=f"{OUT}/study.csv",
    log: f"{LOG}/study.log"
    threads: 1
    params: cfg=STUDY_CFG
    run:
        with logged(log[0]):
            from lfstudy.workflow import run_study
            run_study(CFG, CASES, list(input), BENCH, output.zarr, output.csv)


rule report:
    input:
        study=f"{OUT}/study.zarr",
        errors=expand(f"{OUT}/{{case}}/errors.zarr", case=CASES),
    output: report(f"{OUT}/report.html", caption="reports/report.rst", category="Study")
    log: f"{LOG}/report.log"
    threads: 1
    params: cfg=STUDY_CFG
    run:
        with logged(log[0]):
            from lfstudy.workflow import run_report
            run_report(CFG, CASES, OUT, input.study, output[0])


# Optional, not part of `all`: ParaView and Fiji files of every case.
#   snakemake export --cores all --configfile config/demo.yaml
# (the target before --configfile, which takes several values). piv.vtr and volume_a.vtr
# are rectilinear grids in mm; volume_a.tif is an ImageJ hyperstack with the voxel size.
localrules: export


rule export:
    input: expand(f"{OUT}/{{case}}/{{name}}", case=CASES, name=["piv.vtr", "volume_a.vtr", "volume_a.tif"])


rule export_case:
    input:
        piv=f"{OUT}/{{case}}/piv.zarr",
        volume=f"{OUT}/{{case}}/volume_a.zarr",
    output:
        piv=f"{OUT}/{{case}}/piv.vtr",
        volume_vtk=f"{OUT}/{{case}}/volume_a.vtr",
        volume_tif=f"{OUT}/{{case}}/volume_a.tif",
    log: f"{LOG}/export/{{case}}.log"
    threads: 1
    shell:
        "(python -m lfstudy.cli export {input.piv:q} --out {output.piv:q}"
        " && python -m lfstudy.cli export {input.volume:q} --out {output.volume_vtk:q}"
        " && python -m lfstudy.cli export {input.volume:q} --out {output.volume_tif:q} --resample-z)"
        " > {log:q} 2>&1"
