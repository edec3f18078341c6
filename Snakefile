# lfstudy: the parametric light-field PIV study.
#
#   snakemake --cores all --configfile config/demo.yaml
#
# Per case: camera -> particles -> displace -> simulate (a, b) -> register ->
# refocus -> reconstruct -> piv -> errors; the pinhole image and the lenslet
# calibration are shared (results/<name>/calib/<calib id>/...). The study combines
# every case into study.zarr / study.csv and report.html.
#
# Where a stage writes is given by the sweep table (lfstudy/study/sweep.py): the
# case-id prefix holding exactly the settings the stage depends on. Cases that
# differ only in, say, reconstruct.method share their images, light fields and
# focal stacks; the calibration is shared by every case with the same camera
# (bar the working f-number).
#
# Rule bodies live in lfstudy/workflow.py. Per-case rules are shell commands
# (python -m lfstudy.workflow STAGE ...): far cheaper to start than a run: block,
# which Snakemake executes by spawning a whole new Snakemake. Each gets the config
# sections its stage reads as params, so editing the config reruns exactly the
# stages that depend on the change.
import json
import os
import re
import shlex
import sys

from snakemake.exceptions import WorkflowError

from lfstudy.config import read_yaml
from lfstudy.piv.ptv import PARTICLE_MODES
from lfstudy.reconstruct import gives_particles
from lfstudy.simulate.flows import flow_input_files
from lfstudy.study.config import case_config, stage_config, validate_config
from lfstudy.study.resources import job_mem_mb, job_runtime_min, machine_memory
from lfstudy.study.sweep import SHARED, STAGES, Sweep, frame_stage

# The demo config only when none is given: Snakemake merges a --configfile into the Snakefile's
# `configfile:` key by key, so a study's config would otherwise inherit every demo setting it
# leaves out (its sweep keys, grid, flows) and run cases nobody asked for.
if not workflow.overwrite_configfiles:

    configfile: "config/demo.yaml"

# `--config process=RECORDING.yaml` names a recording for the optional `process` target (end of
# this file); it is no study setting, so it leaves the config before the study is validated.
PROCESS = config.pop("process", None)
# A file flow's relative path is relative to the config file's folder (the last --configfile, made
# absolute by Snakemake; else the Snakefile's own config/demo.yaml); validate_config makes it absolute.
_CONFIG_FILES = list(workflow.overwrite_configfiles) or list(workflow.configfiles)
CONFIG_DIR = os.path.dirname(os.path.abspath(_CONFIG_FILES[-1])) if _CONFIG_FILES else os.getcwd()
# Snakemake reads --configfile keeping the last of a key given twice; lfstudy's reader refuses it.
for _path in _CONFIG_FILES:
    if os.path.isfile(_path):
        read_yaml(_path)
# one clear error on a bad config (PIV windows too large for the volumes included), defaults filled
CFG = validate_config(config, base=CONFIG_DIR, piv_grid=True)
NAME = CFG["name"]
SWEEP = Sweep(CFG)
if workflow.is_main_process:  # the size of what is planned next (a large sweep takes a while)
    print(f"lfstudy: study {NAME!r} sweeps {len(SWEEP)} cases", file=sys.stderr)
CASES = [c.case_id for c in SWEEP.cases()]
IDS = {stage: SWEEP.stage_ids(stage) for stage in STAGES}  # stage -> {where it writes: a case}
# Where the reconstruction fits particles (reconstruct.method: ipr): those jobs also write the
# particle list (rule reconstruct_particles); every other case's rule reconstruct is unchanged.
# Frame a (before the flow moves the particles) has stages of its own, "<stage>_a", written once per
# design and shared by its flows (lfstudy.study.sweep.FRAME_STAGES).
PARTICLE_IDS = {
    f: sorted(
        i
        for i, c in IDS[frame_stage("reconstruct", f)].items()
        if gives_particles(SWEEP.apply(c)["reconstruct"]["method"])
    )
    for f in "ab"
}
OUT = f"results/{NAME}"
LOG = f"{OUT}/logs"
BENCH = f"{OUT}/benchmarks"
# threads of the multi-threaded rules: all cores unless the config caps them
try:
    CORES = workflow.cores
except WorkflowError:  # no --cores: 'snakemake --report', --lint; no job runs
    CORES = 1
HEAVY = min(CORES, CFG["workflow"]["threads_per_job"] or CORES)
# Heavy rules declare mem_mb (their case's estimate, see mem_mb below). The local scheduler weighs
# them against a total only when one is given (--resources mem_mb=N); without one, the total is
# 90 % of this machine's memory (as check_memory), so `--cores N` never runs more heavy jobs side
# by side than the memory holds. A cluster executor (its jobs run elsewhere) is left as it is.
# register_resource and the "_nodes" entry are Snakemake 9 internals (pyproject pins snakemake < 10);
# without them the rules still declare mem_mb, only the local total is not set.
if (
    hasattr(workflow, "register_resource")
    and "mem_mb" not in workflow.global_resources
    and getattr(workflow.global_resources.get("_nodes"), "value", 0) is None
    and machine_memory()
):
    workflow.register_resource("mem_mb", int(0.9 * machine_memory() / 1e6))

wildcard_constraints:
    sid=r"[^/~]+~[^/]+(/[^/~]+~[^/]+)*",
    cid=r"[^/~]+~[^/]+(/[^/~]+~[^/]+)*",
    frame=r"[ab]",


# Jobs run 'python' from PATH: put this interpreter's directory first, so a
# venv's snakemake works without activating the venv. (Not the interpreter's
# path in the command itself: Snakemake would see changed code, and rerun
# everything, whenever it is started through another path or symlink.)
os.environ["PATH"] = os.path.dirname(sys.executable) + os.pathsep + os.environ.get("PATH", "")
STAGE = "python -m lfstudy.workflow --config {params.cfg:q} --log {log:q} --threads {threads}"
# The dask scheduler of refocus, reconstruct and piv (config section compute). Not a param: it
# changes where the tasks run, not their results (bit-identical), so changing it reruns nothing.
COMPUTE = json.dumps(CFG["compute"], sort_keys=True)
DASK_STAGE = STAGE + " --compute {COMPUTE:q}"

# study and report read the whole config: they rerun on any change to it
STUDY_CFG = json.dumps(CFG, sort_keys=True, default=str)


def _case(stage, wildcards):
    """A case whose `stage` output lives at this rule's {sid} (or {cid} for the calibration); for a
    rule of both exposures ({frame}), the stage of that frame (frame a's: shared by the flows)."""
    key = wildcards.cid if stage in SHARED else wildcards.sid
    return IDS[frame_stage(stage, getattr(wildcards, "frame", ""))][key]


def stage_params(stage):
    """params.cfg of a per-stage rule: the stage's config sections as JSON."""
    def cfg(wildcards):
        own = frame_stage(stage, getattr(wildcards, "frame", ""))
        return json.dumps(stage_config(CFG, _case(stage, wildcards), own), sort_keys=True)
    return cfg


def mem_mb(stage):
    """resources.mem_mb of a heavy rule: its case's memory estimate (lfstudy.study.resources.job_mem_mb),
    doubled on a retry. Local runs and SLURM then never start more jobs than the memory holds."""
    def mb(wildcards, attempt):
        return job_mem_mb(SWEEP.apply(_case(stage, wildcards)), stage, attempt)
    return mb


def runtime_min(stage, floor):
    """resources.runtime of a rule whose method may estimate its time (reconstruct: IPR's goes with the
    particles): lfstudy.study.resources.job_runtime_min, at least `floor` minutes, doubled on a retry. The
    SLURM profile sets no runtime for these rules (its set-resources would override this)."""
    def minutes(wildcards, attempt):
        return job_runtime_min(SWEEP.apply(_case(stage, wildcards)), stage, floor, attempt)
    return minutes


def at(name, of):
    """Input function: file `name` (FILES says which stage writes it) for the case behind this rule
    of stage `of`."""
    def path(wildcards):
        loc = SWEEP.locate(_case(of, wildcards), name.format(frame=getattr(wildcards, "frame", "")))
        return f"{OUT}/{loc}"
    return path


def fitted_input(stage):
    """Input function: the particle lists of both frames where the case's method fits particles
    (the errors stage reads them beside the volumes; none for other methods)."""
    def files(wildcards):
        case = _case(stage, wildcards)
        if not gives_particles(SWEEP.apply(case)["reconstruct"]["method"]):
            return []
        return [f"{OUT}/{SWEEP.locate(case, f'volume_{f}.particles.zarr')}" for f in "ab"]
    return files


def flow_files(stage):
    """Input function: the files the case's flow reads (a file flow's zarr store or netCDF file;
    none for an analytic flow), so that editing them reruns the rules that use the flow."""
    def files(wildcards):
        return flow_input_files(SWEEP.apply(_case(stage, wildcards))["flow"])
    return files


localrules: all


# Every intermediate is a target too: Snakemake (>= 7.7) ignores a deleted
# intermediate whose downstream outputs exist, but regenerates a missing
# target, and the newer file then reruns exactly what depends on it.
def every(stage, *names, frame=""):
    ids = sorted(IDS[frame_stage(stage, frame)])
    root = f"{OUT}/calib" if stage in SHARED else OUT
    return [f"{root}/{i}/{n}" for i in ids for n in names]


rule all:
    input:
        f"{OUT}/study.zarr",
        f"{OUT}/study.csv",
        f"{OUT}/report.html",
        every("camera", "camera.json", "focal_planes.zarr"),
        every("particles", "particles_a.zarr"),
        every("displace", "particles_b.zarr"),
        [every("simulate", f"raw_{f}.zarr", f"raw_{f}.tif", frame=f) for f in "ab"],
        every("pinhole", "pinhole.zarr", "pinhole.tif"),
        every("calibrate", "centers.zarr"),
        [every("register", f"lightfield_{f}.zarr", frame=f) for f in "ab"],
        [every("refocus", f"stack_{f}.zarr", frame=f) for f in "ab"],
        [every("reconstruct", f"volume_{f}.zarr", frame=f) for f in "ab"],
        [f"{OUT}/{i}/volume_{f}.particles.zarr" for f in "ab" for i in PARTICLE_IDS[f]],
        every("piv", "piv.zarr"),
        every("errors", "errors.zarr"),


rule camera:
    output:
        json=f"{OUT}/{{sid}}/camera.json",
        planes=directory(f"{OUT}/{{sid}}/focal_planes.zarr"),
    log: f"{LOG}/camera/{{sid}}.log"
    benchmark: f"{BENCH}/camera/{{sid}}.tsv"
    threads: 1
    params: cfg=stage_params("camera")
    shell: STAGE + " camera {output.json:q} {output.planes:q}"


rule particles:
    input: at("camera.json", "particles")
    output: directory(f"{OUT}/{{sid}}/particles_a.zarr")
    log: f"{LOG}/particles/{{sid}}.log"
    benchmark: f"{BENCH}/particles/{{sid}}.tsv"
    threads: 1
    params: cfg=stage_params("particles")
    shell: STAGE + " particles {output[0]:q}"


rule displace:
    input:
        particles=at("particles_a.zarr", "displace"),
        flow=flow_files("displace"),
    output: directory(f"{OUT}/{{sid}}/particles_b.zarr")
    log: f"{LOG}/displace/{{sid}}.log"
    benchmark: f"{BENCH}/displace/{{sid}}.tsv"
    threads: 1
    params: cfg=stage_params("displace")
    shell: STAGE + " displace {input.particles:q} {output[0]:q}"


rule simulate:
    input: at("particles_{frame}.zarr", "simulate")
    output:
        zarr=directory(f"{OUT}/{{sid}}/raw_{{frame}}.zarr"),
        tiff=f"{OUT}/{{sid}}/raw_{{frame}}.tif",
    log: f"{LOG}/simulate/{{sid}}_{{frame}}.log"
    benchmark: f"{BENCH}/simulate/{{sid}}_{{frame}}.tsv"
    threads: HEAVY
    params: cfg=stage_params("simulate")
    resources: mem_mb=mem_mb("simulate")
    shell: STAGE + " simulate {wildcards.frame} {input[0]:q} {output.zarr:q} {output.tiff:q}"


rule pinhole:
    output:
        zarr=directory(f"{OUT}/calib/{{cid}}/pinhole.zarr"),
        tiff=f"{OUT}/calib/{{cid}}/pinhole.tif",
    log: f"{LOG}/pinhole/{{cid}}.log"
    benchmark: f"{BENCH}/pinhole/{{cid}}.tsv"
    threads: HEAVY
    params: cfg=stage_params("pinhole")
    resources: mem_mb=mem_mb("pinhole")
    shell: STAGE + " pinhole {output.zarr:q} {output.tiff:q}"


rule calibrate:
    input: f"{OUT}/calib/{{cid}}/pinhole.zarr"
    output: directory(f"{OUT}/calib/{{cid}}/centers.zarr")
    log: f"{LOG}/calibrate/{{cid}}.log"
    benchmark: f"{BENCH}/calibrate/{{cid}}.tsv"
    threads: HEAVY
    params: cfg=stage_params("calibrate")
    resources: mem_mb=mem_mb("calibrate")
    shell: STAGE + " calibrate {input[0]:q} {output[0]:q}"


rule register:
    input:
        raw=at("raw_{frame}.zarr", "register"),
        centers=at("centers.zarr", "register"),
    output: directory(f"{OUT}/{{sid}}/lightfield_{{frame}}.zarr")
    log: f"{LOG}/register/{{sid}}_{{frame}}.log"
    benchmark: f"{BENCH}/register/{{sid}}_{{frame}}.tsv"
    threads: 1
    params: cfg=stage_params("register")
    resources: mem_mb=mem_mb("register")
    shell: STAGE + " register {input.raw:q} {input.centers:q} {output[0]:q}"


def volcal_input(stage):
    """Input function: the dot-target calibration a stage samples its planes through, where
    refocus.model is volumetric (the thin lens needs none)."""
    def path(wildcards):
        case = _case(stage, wildcards)
        if SWEEP.apply(case)["refocus"].get("model", "thin_lens") != "volumetric":
            return []
        return [f"{OUT}/{SWEEP.locate(case, 'volcal.zarr')}"]
    return path


rule volcal:
    input: at("centers.zarr", "volcal")
    output: directory(f"{OUT}/calib/{{cid}}/volcal.zarr")
    log: f"{LOG}/volcal/{{cid}}.log"
    benchmark: f"{BENCH}/volcal/{{cid}}.tsv"
    threads: HEAVY
    params: cfg=stage_params("volcal")
    resources: mem_mb=mem_mb("volcal")
    shell: STAGE + " volcal {input[0]:q} {output[0]:q}"


rule refocus:
    input:
        lightfield=at("lightfield_{frame}.zarr", "refocus"),
        volcal=volcal_input("refocus"),
    output: directory(f"{OUT}/{{sid}}/stack_{{frame}}.zarr")
    log: f"{LOG}/refocus/{{sid}}_{{frame}}.log"
    benchmark: f"{BENCH}/refocus/{{sid}}_{{frame}}.tsv"
    threads: HEAVY
    params: cfg=stage_params("refocus")
    resources: mem_mb=mem_mb("refocus")
    shell: DASK_STAGE + " refocus {input.lightfield:q} {output[0]:q} {input.volcal:q}"


# Numba compiles each kernel once and caches it, but jobs started side by side each compile it (on a fresh
# clone the demo's first two IPR fits took 78-82 s each, 30-35 s warm). Rule warm compiles the study's kernels
# first, on a tiny copy of one case per reconstruction method (lfstudy.study.warm), at a high priority, while
# the other cores render and register; the reconstructions wait for it. Their input is ancient, and the cases
# are no param (like COMPUTE): warm runs when warm.json is missing, never because the config changed. (A job
# Snakemake reruns masks the checks of every job below it, and ancient then keeps them from rerunning: a warm
# job rerun by a config change would hide that change from the stages it concerns.) Its failure is logged in
# warm.json, never fatal (the stage's own job then reports it).
WARM = f"{OUT}/warm.json"
_WARM_CASES = {}
for _c in SWEEP.cases():  # the first case of each method (its full config made once, not per case)
    _method = SWEEP.apply(_c)["reconstruct"]["method"]
    if _method not in _WARM_CASES:
        _WARM_CASES[_method] = case_config(CFG, _c)
WARM_CFG = json.dumps({"cases": list(_WARM_CASES.values())}, sort_keys=True, default=str)


rule warm:
    output: WARM
    log: f"{LOG}/warm.log"
    benchmark: f"{BENCH}/warm/warm.tsv"
    threads: 1
    priority: 50
    resources: mem_mb=1500
    shell: "python -m lfstudy.workflow warm --config {WARM_CFG:q} --log {log:q} --threads {threads} {output:q}"


rule reconstruct:
    input:
        stack=at("stack_{frame}.zarr", "reconstruct"),
        lightfield=at("lightfield_{frame}.zarr", "reconstruct"),
        centers=at("centers.zarr", "reconstruct"),
        volcal=volcal_input("reconstruct"),
        warm=ancient(WARM),
    output: directory(f"{OUT}/{{sid}}/volume_{{frame}}.zarr")
    log: f"{LOG}/reconstruct/{{sid}}_{{frame}}.log"
    benchmark: f"{BENCH}/reconstruct/{{sid}}_{{frame}}.tsv"
    threads: HEAVY
    params: cfg=stage_params("reconstruct")
    resources: mem_mb=mem_mb("reconstruct"), runtime=runtime_min("reconstruct", 5)
    # '' for the particle list this method does not have, then the volumetric calibration ('' where none)
    shell:
        DASK_STAGE + " reconstruct {input.stack:q} {input.lightfield:q} {input.centers:q} {output[0]:q} ''"
        " {input.volcal:q}"


# A method that fits particles writes the list beside each volume, from the same fit (one job).
# Snakemake's outputs are static per rule, so these cases get a rule of their own, bound to
# their stage ids; it wins over rule reconstruct for their volumes.
if PARTICLE_IDS["a"] or PARTICLE_IDS["b"]:

    ruleorder: reconstruct_particles > reconstruct

    rule reconstruct_particles:
        wildcard_constraints:
            sid="(?:" + "|".join(re.escape(i) for i in sorted({*PARTICLE_IDS["a"], *PARTICLE_IDS["b"]})) + ")",
        input:
            stack=at("stack_{frame}.zarr", "reconstruct"),
            lightfield=at("lightfield_{frame}.zarr", "reconstruct"),
            centers=at("centers.zarr", "reconstruct"),
            volcal=volcal_input("reconstruct"),
            warm=ancient(WARM),
        output:
            volume=directory(f"{OUT}/{{sid}}/volume_{{frame}}.zarr"),
            particles=directory(f"{OUT}/{{sid}}/volume_{{frame}}.particles.zarr"),
        log: f"{LOG}/reconstruct/{{sid}}_{{frame}}.log"
        benchmark: f"{BENCH}/reconstruct/{{sid}}_{{frame}}.tsv"
        threads: HEAVY
        params: cfg=stage_params("reconstruct")
        resources: mem_mb=mem_mb("reconstruct"), runtime=runtime_min("reconstruct", 5)
        shell:
            DASK_STAGE + " reconstruct {input.stack:q} {input.lightfield:q} {input.centers:q}"
            " {output.volume:q} {output.particles:q} {input.volcal:q}"


rule depthcal:
    input:
        centers=at("centers.zarr", "depthcal"),
        volcal=volcal_input("depthcal"),
    output: directory(f"{OUT}/calib/{{cid}}/depth_calibration.zarr")
    log: f"{LOG}/depthcal/{{cid}}.log"
    benchmark: f"{BENCH}/depthcal/{{cid}}.tsv"
    threads: HEAVY
    params: cfg=stage_params("depthcal")
    resources: mem_mb=mem_mb("depthcal")
    shell: DASK_STAGE + " depthcal {input.centers:q} {output[0]:q} {input.volcal:q}"


def depth_input(wildcards):
    """The depth calibration a PIV job divides its w by, or none where it is disabled."""
    case = _case("piv", wildcards)
    if not SWEEP.apply(case)["depth_calibration"]["enabled"]:
        return []
    return [f"{OUT}/{SWEEP.locate(case, 'depth_calibration.zarr')}"]


def depth_arg(wildcards):
    """params.depth of a PIV job: its depth calibration's path, or '' (always one shell word, so the
    particle lists after it keep their place)."""
    return " ".join(shlex.quote(p) for p in depth_input(wildcards)) or "''"


def ptv_input(wildcards):
    """Input function: both frames' particle lists where the PIV job reads them (piv.particles: ptv or
    paired; validation admits them only for a method that fits particles), else none."""
    case = _case("piv", wildcards)
    if SWEEP.apply(case)["piv"].get("particles", "none") not in PARTICLE_MODES:
        return []
    return [f"{OUT}/{SWEEP.locate(case, f'volume_{f}.particles.zarr')}" for f in "ab"]


rule piv:
    input:
        a=at("volume_a.zarr", "piv"),
        b=at("volume_b.zarr", "piv"),
        depth=depth_input,
        particles=ptv_input,  # piv.particles: ptv or paired read the fitted particles of both frames
    output: directory(f"{OUT}/{{sid}}/piv.zarr")
    log: f"{LOG}/piv/{{sid}}.log"
    benchmark: f"{BENCH}/piv/{{sid}}.tsv"
    threads: HEAVY
    params:
        cfg=stage_params("piv"),
        depth=depth_arg,
    resources: mem_mb=mem_mb("piv")
    shell:
        DASK_STAGE + " piv {input.a:q} {input.b:q} {output[0]:q} {params.depth} {input.particles:q}"


rule errors:
    input:
        piv=at("piv.zarr", "errors"),
        volume=at("volume_a.zarr", "errors"),
        particles=at("particles_a.zarr", "errors"),
        # the oracle (the case's PIV on the true volumes of both frames) runs here: seconds
        particles_b=at("particles_b.zarr", "errors"),
        flow=flow_files("errors"),  # the truth: a file flow's field
        fitted=fitted_input("errors"),  # a particle method's lists, read beside the volumes
    output: directory(f"{OUT}/{{sid}}/errors.zarr")
    log: f"{LOG}/errors/{{sid}}.log"
    benchmark: f"{BENCH}/errors/{{sid}}.tsv"
    threads: 1
    params: cfg=stage_params("errors")
    shell:
        STAGE + " errors {input.piv:q} {input.volume:q} {input.particles:q} {output[0]:q} {input.particles_b:q}"
        " {input.fitted:q}"


rule study:
    input: [f"{OUT}/{SWEEP.locate(c, 'errors.zarr')}" for c in CASES]
    output:
        zarr=directory(f"{OUT}/study.zarr"),
        csv=f"{OUT}/study.csv",
    log: f"{LOG}/study.log"
    threads: 1
    params: cfg=STUDY_CFG, out=OUT
    shell: STAGE + " study {params.out:q} {output.zarr:q} {output.csv:q}"


rule report:
    input:
        study=f"{OUT}/study.zarr",
        errors=[f"{OUT}/{SWEEP.locate(c, 'errors.zarr')}" for c in CASES],
    output: report(f"{OUT}/report.html", caption="reports/report.rst", category="Study")
    log: f"{LOG}/report.log"
    # the last job: its per-case figures are drawn by a process per core (at most one per case)
    threads: min(CORES, len(CASES))
    params: cfg=STUDY_CFG, out=OUT
    shell: STAGE + " report {params.out:q} {input.study:q} {output[0]:q}"


# Optional, not part of `all`: ParaView and Fiji files of every case.
#   snakemake export --cores all --configfile config/demo.yaml
# (the target before --configfile, which takes several values). piv.vtr is a
# rectilinear grid in mm; volume_a.vtr and volume_a.tif (an ImageJ hyperstack with
# the voxel size) are written beside the volume they come from.
localrules: export


rule export:
    input:
        every("piv", "piv.vtr"),
        every("reconstruct", "volume_a.vtr", "volume_a.tif", frame="a"),


rule export_piv:
    input: f"{OUT}/{{sid}}/piv.zarr"
    output: f"{OUT}/{{sid}}/piv.vtr"
    log: f"{LOG}/export/{{sid}}_piv.log"
    threads: 1
    shell: "python -m lfstudy.cli export {input:q} --out {output:q} > {log:q} 2>&1"


rule export_volume:
    input: f"{OUT}/{{sid}}/volume_a.zarr"
    output:
        vtk=f"{OUT}/{{sid}}/volume_a.vtr",
        tif=f"{OUT}/{{sid}}/volume_a.tif",
    log: f"{LOG}/export/{{sid}}_volume.log"
    threads: 1
    shell:
        "(python -m lfstudy.cli export {input:q} --out {output.vtk:q}"
        " && python -m lfstudy.cli export {input:q} --out {output.tif:q} --resample-z) > {log:q} 2>&1"


# Optional, not part of `all`: process a recording (calibration image, dark frames, image pairs or
# a time series of plenoptic TIFFs; schema lfstudy/process_schema.yaml) as `lfstudy process` does:
#   snakemake --cores all process --config process=path/to/recording.yaml
# Output: results/<recording name>/ (piv.zarr along time, metrics.csv, report.html, ...). It
# reruns when the recording config or any of its image files changes.
#
# No directory() output: Snakemake clears a job's outputs before it starts, before lfstudy could
# check them, so a recording kept under results/<name>/ or a user's folder there would be lost
# (issue 37). The declared output is results/<name>.process.json, the finished run's marker copied
# beside it (checked at parse time by lfstudy.process.target); `lfstudy process --overwrite`
# itself replaces results/<name>/ only where it holds an earlier output of its own and nothing else.
localrules: process

if PROCESS:
    from lfstudy.process.config import load_process_config
    from lfstudy.process.recording import recording_files
    from lfstudy.process.target import TargetError, process_target

    PCFG = load_process_config(PROCESS)
    try:
        PTARGET = process_target(PROCESS, PCFG["name"], recording_files(PCFG["recording"]))
    except TargetError as exc:
        raise WorkflowError(str(exc)) from None
    if PTARGET.out == OUT:
        raise WorkflowError(
            f"recording {PROCESS!r}: its name {PCFG['name']!r} is the study's; rename one (both write {OUT})"
        )

    def process_mem_mb(wildcards, attempt):
        """resources.mem_mb of the recording's job: every stage of its config (job_mem_mb)."""
        return job_mem_mb(PCFG, "process", attempt)

    rule process:
        input: PTARGET.record

    rule process_recording:
        input:
            config=PROCESS,
            images=PTARGET.inputs[1:],
        output: PTARGET.record
        params: out=PTARGET.out
        log: f"results/{PCFG['name']}.process.log"
        threads: HEAVY
        resources: mem_mb=process_mem_mb
        shell:
            "python -m lfstudy.cli process {input.config:q} --out {params.out:q} --overwrite"
            " --threads {threads} --quiet > {log:q} 2>&1"
            " && cp {params.out:q}/.lfstudy-output.json {output:q}"

else:

    rule process:
        run:
            raise WorkflowError("the process target needs a recording: --config process=RECORDING.yaml")
