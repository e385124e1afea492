"""Label Studio's ML backend (`detmatch review backend`): the served 2D detector pre-annotates
Label Studio's tasks, reviewers' annotations come back into the label store as human labels,
and training requests queue retraining rounds. Written on aiohttp (the `review` extra); the
PyPI `label-studio-ml` package is stale and pins an old Flask.

The protocol (what Label Studio calls):

    GET  /health    {"status": "UP", "model_version", "training": {...}}
    POST /setup     {"project", "schema": the label config XML, "hostname", "access_token"}
                    -> {"model_version"}: the config must hold a RectangleLabels on an Image;
                    the version is VERSION-camera (`camera_version`)
    POST /predict   {"tasks": [...], "project", "label_config"} -> {"results": [one per task:
                    {"result": [rectanglelabels ...], "score", "model_version"}]}: the served
                    version's 2D detections above its score threshold, of the config's labels
    POST /webhook   {"action", "task", "annotation", "project"} -> 201:
                    ANNOTATION_CREATED / ANNOTATION_UPDATED of a `detmatch review export` task
                    (its data.frame names a stored frame) store the annotation as the frame's
                    human labels (`serving.reviews.store_reviews`: checked, never silently
                    overwriting); START_TRAINING, or every --train-after new annotations,
                    queues a retraining round.

Images: a task's image is a data: URI, an http(s) URL, or a path on the Label Studio server
(`/data/...`), fetched from the hostname /setup gave (or --label-studio-url) with its token.

Retraining rounds run one at a time as `detmatch retrain` processes, under the repository's
retraining lock (`retrain.schedule`): requests while a round runs coalesce into one more round
after it; a round refused because another scheduler holds the lock is retried every
--lock-retry-s. The served version is reloaded when the repository promotes a new one.
"""

from __future__ import annotations

import asyncio
import base64
import binascii
import io
import logging
import signal
import subprocess
import sys
import threading
import time
import xml.etree.ElementTree as ElementTree
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import urljoin, urlparse

import numpy as np
from aiohttp import ClientSession, ClientTimeout, web
from PIL import Image, UnidentifiedImageError

from detmatch.constants import RETRAIN_LOCK_HELD_EXIT, REVIEW_CLASSES
from serving.repository import served_version
from serving.review import drawable, rectangle_result
from serving.reviews import ReviewImportError, label_studio_items, store_reviews

log = logging.getLogger("detmatch.review.backend")
ANNOTATION_EVENTS = ("ANNOTATION_CREATED", "ANNOTATION_UPDATED")
TRAINING_EVENT = "START_TRAINING"
MAX_REQUEST_BYTES = 64 * 1024 * 1024
MAX_IMAGE_BYTES = 64 * 1024 * 1024


class BadRequest(ValueError):
    """A request the backend cannot answer, with a message for the caller."""


@dataclass(frozen=True)
class LabelingInterface:
    """The RectangleLabels of a project's label config: what boxes are named from / to and
    which labels they may carry."""

    from_name: str
    to_name: str
    image_key: str  # the task data key of the Image tag ($image -> image)
    labels: tuple[str, ...]


def labeling_interface(config: str) -> LabelingInterface:
    """A project's label config XML -> its first RectangleLabels on an Image (BadRequest if
    it has none)."""
    try:
        root = ElementTree.fromstring(config)
    except ElementTree.ParseError as error:
        raise BadRequest(f"the label config is not XML: {error}") from None
    images = {tag.get("name"): tag.get("value", "") for tag in root.iter("Image")}
    for tag in root.iter("RectangleLabels"):
        target = tag.get("toName")
        if target in images and images[target].startswith("$"):
            labels = tuple(label.get("value") for label in tag.iter("Label") if label.get("value"))
            return LabelingInterface(tag.get("name"), target, images[target][1:], labels)
    raise BadRequest("the label config has no RectangleLabels on an Image: this backend "
                     "pre-annotates boxes on images")  # fmt: skip


@dataclass
class Round:
    """One retraining round: why it was asked for (every request it stands for), when it
    started and finished, how `detmatch retrain` exited and what it printed."""

    reasons: list[str]
    started: float | None = None
    finished: float | None = None
    exit_code: int | None = None
    output: str = ""

    def add(self, reasons: list[str]) -> None:
        """Stand for these requests too."""
        self.reasons += [r for r in reasons if r not in self.reasons]

    @property
    def running(self) -> bool:
        return self.started is not None and self.finished is None

    def summary(self) -> dict[str, Any]:
        return {"reason": "; ".join(self.reasons), "started": self.started,
                "finished": self.finished, "exit_code": self.exit_code,
                "output": self.output[-2000:]}  # fmt: skip


@dataclass
class RetrainQueue:
    """Retraining rounds, one at a time, as `detmatch retrain` processes (see the module
    docstring)."""

    command: list[str]
    lock_retry_s: float = 30.0
    rounds: list[Round] = field(default_factory=list)
    waiting: str | None = None  # why the queued round has not started
    _pending: Round | None = None
    _condition: threading.Condition = field(default_factory=threading.Condition)
    _thread: threading.Thread | None = None
    _process: subprocess.Popen | None = None
    _closed: bool = False

    def request(self, reason: str) -> str:
        """Queue a round: 'started', 'queued' (one runs; this one follows it) or 'already
        queued' (a round after the running one is already waiting)."""
        with self._condition:
            if self._pending is not None:
                self._pending.add([reason])
                return "already queued"
            running = any(r.running for r in self.rounds)
            self._pending = Round([reason])
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name="retrain", daemon=True)
                self._thread.start()
            self._condition.notify_all()
            return "queued" if running else "started"

    def state(self) -> dict[str, Any]:
        with self._condition:
            return {"running": any(r.running for r in self.rounds),
                    "queued": self._pending is not None,
                    "waiting": self.waiting,
                    "rounds": [r.summary() for r in self.rounds]}  # fmt: skip

    def close(self, timeout_s: float = 30.0) -> None:
        """Stop taking rounds; a running round is interrupted (SIGINT: `detmatch retrain`
        resumes it on its next run)."""
        with self._condition:
            self._closed = True
            self._condition.notify_all()
            process = self._process
        if process is not None and process.poll() is None:
            process.send_signal(signal.SIGINT)
        if self._thread is not None:
            self._thread.join(timeout_s)

    def _run(self) -> None:
        while True:
            with self._condition:
                while self._pending is None and not self._closed:
                    self._condition.wait()
                if self._closed:
                    return
                current, self._pending = self._pending, None
                current.started = time.time()
                self.rounds.append(current)
                self._process = subprocess.Popen(
                    self.command, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
                )
            output, _ = self._process.communicate()
            with self._condition:
                exit_code, self._process = self._process.returncode, None
                if exit_code == RETRAIN_LOCK_HELD_EXIT and not self._closed:
                    # Another scheduler holds the repository: wait and try again, one round
                    # for this request and any that came meanwhile.
                    self.rounds.remove(current)
                    current.started = None
                    if self._pending is not None:
                        current.add(self._pending.reasons)
                    self._pending = current
                    self.waiting = (output.strip().splitlines() or ["lock held"])[-1]
                    self._condition.wait(self.lock_retry_s)
                    continue
                current.exit_code, current.output = exit_code, output
                current.finished = time.time()
                self.waiting = None


def camera_version(version: str) -> str:
    """The backend's model_version: the served version's camera detector alone, apart from
    the version's cross-modal labels that `detmatch review export` pre-annotates with (Label
    Studio predicts no task that holds a prediction of the backend's version)."""
    return f"{version}-camera"


def retrain_command(
    store: str, store_root: str | None, data: str, repository: str, overrides: list[str]
) -> list[str]:
    command = [sys.executable, "-m", "commands.main", "retrain", "--store", store,
               "--data", data, "--repository", repository]  # fmt: skip
    if store_root:
        command += ["--store-root", store_root]
    for override in overrides:
        command += ["--set", override]
    return command


class Backend:
    """The backend's state: the served model (reloaded on promotion), the store, the projects
    Label Studio set up and the retraining queue."""

    def __init__(
        self,
        repository: Path,
        store=None,
        queue: RetrainQueue | None = None,
        train_after: int | None = None,
        label_studio_url: str | None = None,
        classes: tuple[str, ...] = REVIEW_CLASSES,
    ) -> None:
        self.repository = Path(repository)
        self.store = store
        self.queue = queue
        self.train_after = train_after
        self.label_studio_url = label_studio_url
        self.classes = classes
        self.projects: dict[str, dict[str, Any]] = {}
        self.new_annotations = 0
        self._labeler = None
        self._model_lock = threading.Lock()
        self._count_lock = threading.RLock()

    # --- the model -------------------------------------------------------------------------

    def _served_labeler(self):
        """The served version's labeler, loaded again when a new version is promoted (call
        with _model_lock held)."""
        from serving.labeler import Labeler

        version = served_version(self.repository)
        if version is None:
            raise BadRequest(f"model repository {self.repository} has no promoted version")
        if self._labeler is None or self._labeler.version != version:
            self._labeler = Labeler.from_repository(self.repository, version)
        return self._labeler

    def model_version(self) -> str:
        return camera_version(served_version(self.repository) or "none")

    def predict_image(self, image: np.ndarray, interface: LabelingInterface) -> dict[str, Any]:
        with self._model_lock:
            labeler = self._served_labeler()
            detections = labeler.detect_2d(image)
        height, width = image.shape[:2]
        results, scores = [], []
        for index in np.flatnonzero(detections.scores >= labeler.score_threshold_2d):
            name = labeler.classes[int(detections.classes[index])]
            if interface.labels and name not in interface.labels:
                continue
            score = float(detections.scores[index])
            box = np.clip(detections.boxes[index], 0, [width, height, width, height])
            if not drawable(box):
                continue  # wholly beyond the image's edge, or empty: no region to draw
            results.append(rectangle_result(f"p{index}", box.tolist(), name, score,
                                            (width, height), from_name=interface.from_name,
                                            to_name=interface.to_name))  # fmt: skip
            scores.append(score)
        return {"result": results, "score": float(np.mean(scores)) if scores else 0.0,
                "model_version": camera_version(labeler.version)}  # fmt: skip

    # --- webhooks ----------------------------------------------------------------------------

    def annotation(self, payload: dict[str, Any]) -> dict[str, Any]:
        task, annotation = payload.get("task"), payload.get("annotation")
        if not isinstance(task, dict) or not isinstance(annotation, dict):
            raise BadRequest(f"{payload.get('action')} without a task and an annotation")
        if self.store is None:
            return {"stored": False, "why": "no --store: annotations are not kept"}
        if not isinstance(task.get("data"), dict) or "frame" not in task["data"]:
            return {"stored": False, "why": "not a `detmatch review export` task (no data.frame)"}
        problems: list[str] = []
        items = label_studio_items([{**task, "annotations": [annotation]}], problems)
        summary = store_reviews(self.store, items, "label-studio", self.classes, problems,
                                f"task {task.get('id')}")  # fmt: skip
        answer: dict[str, Any] = {"stored": True, "created": list(summary.created),
                                  "unchanged": list(summary.unchanged),
                                  "replaced": list(summary.replaced)}  # fmt: skip
        with self._count_lock:  # webhooks run on executor threads
            self.new_annotations += 1
            if self.train_after and self.new_annotations >= self.train_after:
                answer["training"] = self.train(f"{self.new_annotations} new annotations")
        return answer

    def train(self, reason: str) -> str:
        if self.queue is None:
            raise BadRequest("training needs --data and --store (the round's labeled frames "
                             "and its pool)")  # fmt: skip
        with self._count_lock:
            self.new_annotations = 0
        return self.queue.request(reason)


async def _fetch_image(
    backend: Backend, url: str, project: dict[str, Any], session: ClientSession
) -> np.ndarray:
    if url.startswith("data:"):
        try:
            data = base64.b64decode(url.partition(",")[2], validate=True)
        except (binascii.Error, ValueError) as error:
            raise BadRequest(f"an image data URI does not decode: {error}") from None
    else:
        host = project.get("hostname") or backend.label_studio_url
        if not urlparse(url).scheme:
            if not host:
                raise BadRequest(f"image {url!r} is a path on the Label Studio server, and no "
                                 "hostname came with /setup (set --label-studio-url)")  # fmt: skip
            url = urljoin(host, url)
        headers = {}
        token = project.get("access_token")
        if token and host and urlparse(url).netloc == urlparse(host).netloc:
            headers["Authorization"] = f"Token {token}"
        async with session.get(url, headers=headers) as response:
            if response.status != 200:
                raise BadRequest(f"image {url}: HTTP {response.status}")
            data = bytearray()
            async for chunk in response.content.iter_chunked(1 << 16):
                data += chunk
                if len(data) > MAX_IMAGE_BYTES:
                    raise BadRequest(f"image {url}: larger than {MAX_IMAGE_BYTES} bytes")
    try:
        return np.asarray(Image.open(io.BytesIO(bytes(data))).convert("RGB"))
    except (UnidentifiedImageError, OSError) as error:
        raise BadRequest(f"image {url[:80]}: not an image ({error})") from None


def _project_id(payload: dict[str, Any]) -> str:
    """Label Studio's project of a call ("ID.TIMESTAMP" -> "ID")."""
    return str(payload.get("project", "")).split(".")[0]


def make_app(backend: Backend) -> web.Application:
    routes = web.RouteTableDef()

    async def body(request: web.Request) -> dict[str, Any]:
        try:
            payload = await request.json()
        except ValueError as error:
            raise BadRequest(f"the body is not JSON: {error}") from None
        if not isinstance(payload, dict):
            raise BadRequest("the body is not a JSON object")
        return payload

    @routes.get("/health")
    @routes.get("/")
    async def health(request: web.Request) -> web.Response:
        training = backend.queue.state() if backend.queue else None
        return web.json_response({"status": "UP", "model_class": "DetMatch",
                                  "model_version": backend.model_version(),
                                  "training": training})  # fmt: skip

    @routes.post("/setup")
    async def setup(request: web.Request) -> web.Response:
        payload = await body(request)
        interface = labeling_interface(str(payload.get("schema") or ""))
        backend.projects[_project_id(payload)] = {"interface": interface,
                                     "hostname": payload.get("hostname"),
                                     "access_token": payload.get("access_token")}  # fmt: skip
        return web.json_response({"model_version": backend.model_version()})

    @routes.post("/predict")
    async def predict(request: web.Request) -> web.Response:
        payload = await body(request)
        tasks = payload.get("tasks")
        if not isinstance(tasks, list):
            raise BadRequest("predict needs a list of tasks")
        project = backend.projects.get(_project_id(payload), {})
        config = payload.get("label_config")
        interface = labeling_interface(config) if config else project.get("interface")
        if interface is None:
            raise BadRequest("predict needs a label_config (or a /setup of the project first)")
        results = []
        async with ClientSession(timeout=ClientTimeout(total=60)) as session:
            for task in tasks:
                data = task.get("data") if isinstance(task, dict) else None
                url = data.get(interface.image_key) if isinstance(data, dict) else None
                if not isinstance(url, str):
                    raise BadRequest(f"a task has no data.{interface.image_key} image")
                image = await _fetch_image(backend, url, project, session)
                loop = asyncio.get_running_loop()
                results.append(await loop.run_in_executor(
                    None, backend.predict_image, image, interface))  # fmt: skip
        return web.json_response({"results": results, "model_version": backend.model_version()})

    @routes.post("/webhook")
    async def webhook(request: web.Request) -> web.Response:
        payload = await body(request)
        action = payload.get("action")
        if action in ANNOTATION_EVENTS:
            loop = asyncio.get_running_loop()
            answer = await loop.run_in_executor(None, backend.annotation, payload)
        elif action == TRAINING_EVENT:
            answer = {"training": backend.train("START_TRAINING")}
        else:
            answer = {"ignored": str(action)}
        return web.json_response({"action": action, **answer}, status=201)

    @web.middleware
    async def errors(request: web.Request, handler) -> web.StreamResponse:
        try:
            return await handler(request)
        except BadRequest as error:
            log.warning("%s %s: 400 %s", request.method, request.path, error)
            return web.json_response({"error": str(error)}, status=400)
        except ReviewImportError as error:
            log.warning("%s %s: 422 %s", request.method, request.path, error)
            return web.json_response({"error": str(error)}, status=422)

    app = web.Application(middlewares=[errors], client_max_size=MAX_REQUEST_BYTES)
    app.add_routes(routes)
    return app


def serve(backend: Backend, host: str, port: int) -> None:
    """Run until interrupted, printing the address once listening (port 0: a free one)."""

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(message)s")

    async def main() -> None:
        runner = web.AppRunner(make_app(backend), access_log=None)
        await runner.setup()
        site = web.TCPSite(runner, host, port)
        await site.start()
        bound = runner.addresses[0][1]
        print(f"Label Studio ML backend listening on http://{host}:{bound} "
              f"(model version {backend.model_version()})", flush=True)  # fmt: skip
        try:
            await asyncio.Event().wait()
        finally:
            await runner.cleanup()

    try:
        asyncio.run(main())
    finally:
        if backend.queue is not None:
            backend.queue.close()
