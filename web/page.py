"""The web page: Gradio components mounted into the FastAPI app, talking to the same JobService as /api.

Upload (Gradio's file widget shows the upload's progress), the job list, the selected job's state with
a progress bar and its stages, the chosen frames, the camera path, the loss curve, the (textured) GLB in
Gradio's 3-D viewer with its face count and file sizes, and the download in every format. A timer polls the job store once a second. Everything the page needs
ships inside the gradio wheel: no CDN, no internet.

The page shows a job's files straight from its folder (the jobs folder is one of Gradio's static paths),
never copies: they are gone with the job, and ``web.guard.PageGuard`` hands each one out only to whoever
sees the job. With tokens on, the guard lets through only callers with a valid token (``/login`` keeps one
in a cookie) and Gradio tells the handlers whose they are (``auth_dependency``: the owner key as the user).
"""

from __future__ import annotations

import html
from collections.abc import Callable
from pathlib import Path
from typing import Any

import gradio as gr
import pandas as pd
from fastapi import FastAPI, Request
from gradio.data_classes import FileData

from service.auth import TokenAuth
from service.jobs import JobOptions, JobRecord, JobRejected, JobService
from web.guard import PageGuard, add_login_routes, client_of, page_token, page_upload

POLL_S = 1.0
AUTO_PRESET = "auto (the worker's device: quick on a CPU, gpu on CUDA)"
CSS = """
#neudf-status progress { width: 100%; height: 1.2rem; accent-color: #2f6fde; }
#neudf-status table { width: 100%; border-collapse: collapse; font-size: 0.9rem; margin-top: 0.5rem; }
#neudf-status td, #neudf-status th { padding: 2px 6px; border-bottom: 1px solid #ddd; text-align: left; }
#neudf-status .state-failed { color: #b00020; } #neudf-status .state-succeeded { color: #1b7f3b; }
"""
# System fonts only: the default theme would fetch web fonts from the internet.
FONTS = ["ui-sans-serif", "system-ui", "sans-serif"]
MONO = ["ui-monospace", "monospace"]


def _upload_path(payload: FileData | None) -> str | None:
    return None if payload is None else payload.path


def _artifact_path(service: JobService, job_id: str, name: str, owner: str | None) -> str | None:
    try:
        return str(service.artifact(job_id, name, owner))
    except JobRejected:
        return None


def _status_html(job: JobRecord | None) -> str:
    if job is None:
        return "<div id='neudf-job' data-state='none'><p>No job selected. Upload a video or pick one from the list.</p></div>"
    rows = "".join(
        f"<tr><td>{s.name}</td><td>{s.state}</td><td>{100 * s.progress:.0f}%</td>"
        f"<td>{'' if s.seconds is None else f'{s.seconds:.1f} s'}</td><td>{s.runs}</td>"
        f"<td>{'' if s.eta_s is None else f'{s.eta_s:.0f} s'}</td></tr>"
        for s in job.stages
    )
    error = ""
    if job.error:
        error = (f"<p class='state-failed'>Failed in <b>{html.escape(job.error.get('stage', ''))}</b>: "
                 f"{html.escape(job.error.get('message', ''))}</p>")
    registered = job.metrics.get("frames_registered")
    facts = f" &middot; {registered}/{job.metrics.get('frames_total')} frames registered" if registered else ""
    return (
        f"<div id='neudf-job' data-job='{job.id}' data-state='{job.state}' data-progress='{job.progress:.4f}'>"
        f"<p><b>Job {job.id[:8]}</b> ({html.escape(job.input_name)}): "
        f"<span class='state-{job.state}'>{job.state}</span>"
        f"{' &middot; stage ' + job.stage if job.stage else ''} &middot; {100 * job.progress:.1f}%{facts}</p>"
        f"<progress id='neudf-progress' max='1' value='{job.progress:.4f}'></progress>"
        f"<p>{html.escape(job.message)}</p>{error}"
        "<table><tr><th>stage</th><th>state</th><th>progress</th><th>time</th><th>runs</th><th>eta</th></tr>"
        f"{rows}</table></div>"
    )


DOWNLOADS = ("mesh.glb", "mesh.obj", "mesh.mtl", "mesh.png", "mesh.usdz", "mesh.ply")


def _size(nbytes: int) -> str:
    return f"{nbytes / 2**20:.1f} MB" if nbytes >= 2**20 else f"{nbytes / 2**10:.0f} KB"


def _download_html(job: JobRecord, files: dict[str, str]) -> str:
    """The downloaded mesh in figures: its faces (before decimation too), the texture, each file's size."""
    if not files:
        return ""
    faces, before = job.metrics.get("mesh_faces"), job.metrics.get("mesh_faces_before")
    shape = f"{faces:,} faces" if faces is not None else ""
    if faces is not None and before is not None and before != faces:
        shape += f" (decimated from {before:,})"
    texture = job.metrics.get("texture_size")
    shape += f", {texture} px texture" if texture else ", vertex colours"
    sizes = " &middot; ".join(f"{name} {_size(Path(path).stat().st_size)}" for name, path in files.items())
    return f"<div id='neudf-download-info'><p><b>Mesh:</b> {html.escape(shape)}</p><p>{sizes}</p></div>"


def _jobs_table(jobs: list[JobRecord]) -> pd.DataFrame:
    return pd.DataFrame(
        [[j.id[:8], j.input_name, j.state, j.stage or "", f"{100 * j.progress:.0f}%", j.created_at.strftime("%m-%d %H:%M")]
         for j in jobs],
        columns=["job", "video", "state", "stage", "progress", "created (UTC)"],
    )


def _loss_frame(service: JobService, job: JobRecord) -> pd.DataFrame | None:
    rows = [r for r in service.training_log(job) if "iter" in r and "loss" in r]
    return pd.DataFrame({"iter": [r["iter"] for r in rows], "loss": [r["loss"] for r in rows]}) if rows else None


def build_page(service: JobService) -> gr.Blocks:
    settings = service.settings

    def owner_of(request: gr.Request) -> str | None:
        """The owner key Gradio got from ``auth_dependency`` (the guard let only valid tokens through)."""
        if not settings.auth_enabled:
            return None
        if not request.username:
            raise JobRejected(401, "sign in at /login")
        return request.username

    def submit(file: str | None, preset: str, minutes: float | None, frames: float | None, iters: float | None,
               resolution: float | None, threshold: float | None, min_faces: float | None, min_seen: float | None,
               faces: float | None, texture_size: float | None, request: gr.Request) -> tuple[str | None, str, None]:
        if not file:
            raise gr.Error("Choose a video first.")
        fields = {"preset": preset} if preset else {}
        for key, value in (("frames", frames), ("iters", iters), ("mesh_resolution", resolution),
                           ("mesh_min_faces", min_faces)):
            if value:
                fields[key] = str(int(value))
        if minutes:
            fields["minutes"] = str(float(minutes))
        if threshold:
            fields["mesh_threshold"] = str(float(threshold))
        for key, value in (("mesh_min_seen", min_seen), ("faces", faces), ("texture_size", texture_size)):
            if value is not None:  # 0 is a choice here: keep every face, no texture
                fields[key] = str(float(value)) if key == "mesh_min_seen" else str(int(value))
        try:
            upload = page_upload(file)
            job = service.create_from_file(upload, upload.name, fields, owner_of(request))
        except JobRejected as exc:
            raise gr.Error(exc.detail) from None
        upload.unlink(missing_ok=True)  # the job keeps its own copy; the page's goes at once
        return job.id, f"Job {job.id[:8]} queued.", None

    def cancel(job_id: str | None, request: gr.Request) -> str:
        if not job_id:
            return "No job selected."
        try:
            service.cancel(job_id, owner_of(request))
        except JobRejected as exc:
            return exc.detail
        return f"Cancel requested for job {job_id[:8]}."

    def pick(ids: list[str], evt: gr.SelectData) -> str | None:
        row = evt.index[0] if isinstance(evt.index, list | tuple) else evt.index
        try:
            return ids[int(row)]
        except (IndexError, TypeError, ValueError):
            return None

    def refresh(job_id: str | None, shown: dict[str, Any], request: gr.Request) -> tuple:
        try:
            owner = owner_of(request)
            jobs, _ = service.list(owner, limit=50)
            job = service.get(job_id, owner) if job_id else None
        except JobRejected:
            jobs, job = [], None
        table, ids = _jobs_table(jobs), [j.id for j in jobs]
        status = _status_html(job)
        if job is None:
            return (table, ids, status, None, None, None, None, gr.DownloadButton(value=None, visible=False), "", None,
                    {})
        # Heavy widgets change only when their file did: a timer tick must not reload the 3-D view.
        names = set(job.artifacts)
        signature = {"job": job.id, "artifacts": sorted(names), "loss_rows": None}
        loss = _loss_frame(service, job)
        signature["loss_rows"] = None if loss is None else len(loss)
        same_job = shown.get("job") == job.id
        same_files = same_job and shown.get("artifacts") == signature["artifacts"]

        def keep_or(value_fn: Callable[[], Any]) -> Any:
            return gr.skip() if same_files else value_fn()

        frames = keep_or(lambda: [str(p) for p in service.frames(job.id, owner)] or None)
        cameras = keep_or(lambda: _artifact_path(service, job.id, "cameras.png", owner))
        model_path = _artifact_path(service, job.id, "mesh.glb", owner) if not same_files else None
        model = gr.skip() if same_files else model_path
        download = keep_or(lambda: gr.DownloadButton(value=model_path, visible=model_path is not None))
        files = {} if same_files else {n: p for n in DOWNLOADS if (p := _artifact_path(service, job.id, n, owner))}
        info = gr.skip() if same_files else _download_html(job, files)
        others = gr.skip() if same_files else (list(files.values()) or None)
        loss_out = gr.skip() if same_job and shown.get("loss_rows") == signature["loss_rows"] else loss
        return table, ids, status, frames, cameras, loss_out, model, download, info, others, signature

    theme = gr.themes.Default(font=FONTS, font_mono=MONO)
    # Page uploads not turned into a job go after an hour.
    with gr.Blocks(title="NeUDF: video to open mesh", analytics_enabled=False, delete_cache=(600, 3600)) as page:
        page.neudf_theme, page.neudf_css = theme, CSS  # mount_page passes them to gradio
        gr.Markdown("## NeUDF: phone video in, open-surface mesh out\nUpload a walk-around video of an object; "
                    "the job runs frames → poses → scene → train → mesh → export. The same jobs are at "
                    "[/api/jobs](/api/jobs) ([API docs](/docs)).")
        job_id = gr.State(None)
        job_ids = gr.State([])  # the full ids of the rows of the job table
        shown = gr.State({})
        with gr.Row():
            with gr.Column(scale=1, min_width=300):
                if settings.auth_enabled:
                    gr.HTML("<form method='post' action='/logout'><button type='submit'>Sign out</button></form>")
                video = gr.File(label="Video", file_types=["video"], type="filepath", elem_id="neudf-upload")
                # gr.File's own preprocess leaves an empty temporary file in Gradio's folder on every call (and a
                # subclass would make Gradio write a .pyi beside this module); the handler only needs the path,
                # and checks it (a page upload, and a video).
                video.preprocess = _upload_path
                presets = [(AUTO_PRESET, "")] + [(name, name) for name in service.presets()]
                preset = gr.Dropdown(presets, value=settings.default_preset or "", label="Preset")
                minutes = gr.Number(label="Training minutes", value=None, minimum=0, elem_id="neudf-minutes",
                                    info="0 or empty: the default budget")
                with gr.Accordion("Options (empty: the preset's defaults)", open=False, elem_id="neudf-options"):
                    with gr.Row():
                        frames = gr.Number(label="Frames", value=None, precision=0, minimum=0)
                        iters = gr.Number(label="Iterations", value=None, precision=0, minimum=0)
                    with gr.Row():
                        resolution = gr.Number(label="Mesh resolution", value=None, precision=0, minimum=0)
                        threshold = gr.Number(label="Mesh threshold", value=None, minimum=0)
                        min_faces = gr.Number(label="Smallest piece (faces)", value=None, precision=0, minimum=0)
                        min_seen = gr.Number(label="Share of cameras that must see a face", value=None, minimum=0,
                                             maximum=1)
                    with gr.Row():
                        faces = gr.Number(label="Faces of the download", value=None, precision=0, minimum=0,
                                          info=f"empty: {JobOptions.model_fields['faces'].default:,}; 0: every face")
                        texture_size = gr.Number(label="Texture size (px)", value=None, precision=0, minimum=0,
                                                 info=f"empty: {JobOptions.model_fields['texture_size'].default}; "
                                                      "0: vertex colours only")
                submit_btn = gr.Button("Reconstruct", variant="primary", elem_id="neudf-submit")
                notice = gr.Markdown(elem_id="neudf-notice")
                jobs = gr.Dataframe(label="Jobs (click one)", interactive=False, elem_id="neudf-jobs", max_height=320)
            with gr.Column(scale=2):
                status = gr.HTML(_status_html(None), elem_id="neudf-status")
                cancel_btn = gr.Button("Cancel job", size="sm", variant="stop")
                with gr.Row():
                    model = gr.Model3D(label="Mesh (GLB)", elem_id="neudf-model", height=420,
                                       clear_color=(0.95, 0.95, 0.95, 1.0))
                with gr.Row():
                    download = gr.DownloadButton("Download GLB", visible=False, elem_id="neudf-download")
                download_info = gr.HTML("", elem_id="neudf-download-figures")
                downloads = gr.File(label="All formats (GLB, OBJ + MTL + PNG, USDZ for iPhone AR, PLY)",
                                    file_count="multiple", interactive=False, elem_id="neudf-downloads")
                with gr.Row():
                    loss = gr.LinePlot(x="iter", y="loss", label="Loss", elem_id="neudf-loss", height=240)
                    cameras = gr.Image(label="Camera path", elem_id="neudf-cameras", interactive=False)
                gallery = gr.Gallery(label="Chosen frames", elem_id="neudf-frames", columns=8, height=220)

        outputs = [jobs, job_ids, status, gallery, cameras, loss, model, download, download_info, downloads, shown]
        submit_btn.click(submit, [video, preset, minutes, frames, iters, resolution, threshold, min_faces, min_seen,
                                  faces, texture_size],
                         [job_id, notice, video]).then(refresh, [job_id, shown], outputs)
        cancel_btn.click(cancel, [job_id], [notice])
        jobs.select(pick, [job_ids], [job_id]).then(refresh, [job_id, shown], outputs)
        timer = gr.Timer(POLL_S)
        timer.tick(refresh, [job_id, shown], outputs, show_progress="hidden")
        page.load(refresh, [job_id, shown], outputs)
    return page


def mount_page(app: FastAPI) -> None:
    """Mount the page at / of an app ``service.app.create_app`` built (its job service and token checks in
    ``app.state``), with the login routes and the guard in front of it. `neudf serve` calls this."""
    service: JobService = app.state.service
    auth: TokenAuth = app.state.auth
    page = build_page(service)

    def page_owner(request: Request) -> str | None:
        try:
            return auth.owner(page_token(request), client_of(request))
        except JobRejected:
            return None

    add_login_routes(app, auth)  # before the page: its mount at / takes every path not routed yet
    gr.set_static_paths([service.files_root])
    gr.mount_gradio_app(app, page, path="/", footer_links=[], ssr_mode=False,
                        max_file_size=int(service.settings.max_upload_bytes), theme=page.neudf_theme,
                        css=page.neudf_css, auth_dependency=page_owner if auth.enabled else None)
    app.add_middleware(PageGuard, service=service, auth=auth)

