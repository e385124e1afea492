"""The server's edge: one `grpc.aio` interceptor every call passes, whatever its fate.

For each call it
- counts it (requests, errors, latency, in flight; `serving.metrics`) with the status code the
  client got, rejected calls included;
- checks the bearer token before reading anything (health is exempt);
- receives the request message itself, with a time limit (a client that sends headers and
  part of a message, then nothing, is dropped with DEADLINE_EXCEEDED after
  `receive_timeout_s`; it never holds a thread, the server being asyncio); one connection
  (peer) may have at most `max_uploads_per_peer` labeling requests still uploading;
- admits a labeling call (LabelFrame: the limited methods) only once its whole message has
  arrived, so a stream still uploading holds no slot: at most `max_concurrent_rpcs` at once,
  and the bytes they hold (ByteBudget: the message x MESSAGE_COST, for its parsed copy and
  decoded arrays) within `max_inflight_bytes`; a call that does not fit waits up to
  `budget_wait_s`, then gets RESOURCE_EXHAUSTED naming the limit. GetModelInfo, health and
  reflection are never refused because of labeling load;
- parses it itself: bytes that are not the method's message are INVALID_ARGUMENT (gRPC's own
  deserialisation would answer INTERNAL and log a traceback);
- logs what clients get wrong (bad token, bad bytes, too slow, cancelled, over a limit) as one
  WARNING line per kind every `warning_interval_s` at most, no traceback, with the count of
  lines left out, and counts each kind (`detmatch_client_errors_total`); server faults stay
  ERROR with their traceback.

Unary-request handlers are served as stream-request handlers to do this: on the wire a unary
call is a stream of one message, and the handler then starts at the call's start rather than
after a whole message arrived. A message over the transport's size limit is refused by gRPC
itself (RESOURCE_EXHAUSTED to the client); the handler then sees no message and an
already-finished call, and counts it as RESOURCE_EXHAUSTED.
"""

from __future__ import annotations

import asyncio
import contextvars
import hmac
import inspect
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import grpc

from serving.metrics import ServiceMetrics

log = logging.getLogger("detmatch.serving")

HEALTH_PREFIX = "/grpc.health.v1.Health/"
REFLECTION_PREFIXES = (
    "/grpc.reflection.v1alpha.ServerReflection/",
    "/grpc.reflection.v1.ServerReflection/",
)
UNKNOWN_METHOD = "unknown"  # metrics label of unknown methods (never the client's string)
# Fields a handler adds to its call's log line (see `call_fields`).
_CALL_FIELDS: contextvars.ContextVar[dict[str, Any]] = contextvars.ContextVar("call_fields")


def call_fields() -> dict[str, Any]:
    """The current call's log fields: a handler adds what its log line should say."""
    try:
        return _CALL_FIELDS.get()
    except LookupError:
        return {}


# What a labeling call holds per byte of its request message while it runs: the message, the
# parsed protobuf's copy of its image and point bytes, and the decoded arrays (measured on
# 62 MB frames: BENCHMARKS.md, "Heavy and stalled clients").
MESSAGE_COST = 3
DEFAULT_INFLIGHT_BYTES = 512 * 1024 * 1024


@dataclass(frozen=True)
class EdgeSettings:
    token: str | None = None  # None: no authentication
    max_concurrent_rpcs: int = 64
    receive_timeout_s: float = 30.0
    warning_interval_s: float = 10.0
    max_inflight_bytes: int = DEFAULT_INFLIGHT_BYTES
    budget_wait_s: float = 5.0
    max_uploads_per_peer: int = 16

    def __post_init__(self) -> None:
        if self.token is not None and not self.token:
            raise ValueError("token: empty; give a token or None (authentication off)")
        for name in ("max_concurrent_rpcs", "max_inflight_bytes", "max_uploads_per_peer"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not self.receive_timeout_s > 0:
            raise ValueError(f"receive_timeout_s must be > 0, got {self.receive_timeout_s}")
        if not self.budget_wait_s >= 0:
            raise ValueError(f"budget_wait_s must be >= 0, got {self.budget_wait_s}")


class ByteBudget:
    """Bytes that admitted calls hold, within `limit`, on one event loop. A reservation that
    does not fit waits (in arrival order) up to wait_s; the bytes waiting are bounded by the
    limit too, since a waiting call holds its message already."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.used = 0
        self.waiting = 0
        self._freed = asyncio.Condition()

    async def reserve(self, size: int, wait_s: float) -> bool:
        """True once `size` bytes are reserved (release them with `release`); False when they
        cannot be within wait_s (or never: a size over the limit)."""
        if size > self.limit:
            return False
        if self.used + size <= self.limit and not self.waiting:
            self.used += size
            return True
        if self.waiting + size > self.limit or wait_s <= 0:
            return False
        self.waiting += size
        try:
            async with self._freed:
                await asyncio.wait_for(
                    self._freed.wait_for(lambda: self.used + size <= self.limit), wait_s
                )
                self.used += size
                return True
        except asyncio.TimeoutError:
            return False
        finally:
            self.waiting -= size

    async def release(self, size: int) -> None:
        self.used -= size
        async with self._freed:
            self._freed.notify_all()


class RateLimitedWarnings:
    """At most one WARNING line per kind every interval_s seconds; the next one says how many
    were left out. Every one is counted in `counter` (a Prometheus counter by kind) if given."""

    def __init__(self, interval_s: float, counter=None) -> None:
        self.interval_s = interval_s
        self.counter = counter
        self._last: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}

    def warning(self, kind: str, message: str, fields: dict[str, Any]) -> None:
        if self.counter is not None:
            self.counter.labels(kind).inc()
        now = time.monotonic()
        if now - self._last.get(kind, -float("inf")) < self.interval_s:
            self._suppressed[kind] = self._suppressed.get(kind, 0) + 1
            return
        self._last[kind] = now
        suppressed = self._suppressed.pop(kind, 0)
        log.warning(message, extra={"fields": {**fields, "suppressed_since_last": suppressed}})


class _GrpcClientErrors(logging.Filter):
    """grpc's own ERROR records that a client causes (a header value that is not UTF-8,
    logged with a traceback by its metadata decoder), turned into the serving edge's
    rate-limited warning of that kind. Installed once on grpc's logger; the newest edge
    counts them."""

    MESSAGES = {"Invalid encoding on %s": ("header not UTF-8", "a header value is not UTF-8")}

    def __init__(self) -> None:
        super().__init__()
        self.warnings: RateLimitedWarnings | None = None

    def filter(self, record: logging.LogRecord) -> bool:
        known = self.MESSAGES.get(record.msg) if isinstance(record.msg, str) else None
        if known is None:
            return True
        if self.warnings is not None:
            value = str(record.args[0])[:80] if record.args else ""
            self.warnings.warning(known[0], known[1], {"value": value})
        return False


_GRPC_CLIENT_ERRORS = _GrpcClientErrors()
logging.getLogger("grpc._cython.cygrpc").addFilter(_GRPC_CLIENT_ERRORS)


class _Rejected(Exception):
    """The call ended before the handler ran; code: what the client got."""

    def __init__(self, code: grpc.StatusCode) -> None:
        super().__init__(code.name)
        self.code = code


class EdgeInterceptor(grpc.aio.ServerInterceptor):
    def __init__(
        self,
        settings: EdgeSettings,
        metrics: ServiceMetrics,
        model_version: Callable[[], str | None],
        logged_prefix: str,
        limited_methods: frozenset[str],
    ) -> None:
        """logged_prefix: calls of methods under it (the labeling service) get a log line;
        limited_methods: paths of the heavy methods, admitted by slots and the byte budget;
        model_version: the served version, for the metrics' label."""
        self.settings = settings
        self.metrics = metrics
        self.model_version = model_version
        self.logged_prefix = logged_prefix
        self.limited_methods = limited_methods
        self.warnings = RateLimitedWarnings(settings.warning_interval_s, metrics.client_errors)
        _GRPC_CLIENT_ERRORS.warnings = self.warnings
        self.in_flight = 0
        self.uploading: dict[str, int] = {}  # peer -> limited calls still receiving
        self._budget: ByteBudget | None = None  # made on the server's event loop
        self._token = None if settings.token is None else settings.token.encode()

    @property
    def budget(self) -> ByteBudget:
        if self._budget is None:
            self._budget = ByteBudget(self.settings.max_inflight_bytes)
        return self._budget

    async def intercept_service(self, continuation, handler_call_details):
        handler = await continuation(handler_call_details)
        path = handler_call_details.method
        if handler is None:
            self.metrics.observe(UNKNOWN_METHOD, grpc.StatusCode.UNIMPLEMENTED, 0.0, None)
            self.warnings.warning("unknown method", "call of an unknown method",
                                  {"method": path[:100]})  # fmt: skip
            return None
        authorized = self._authorized(path, handler_call_details.invocation_metadata)
        return _wrap(handler, self._run(path, authorized, handler))

    def _authorized(self, path: str, metadata) -> bool:
        """One `authorization: Bearer TOKEN` header (the scheme in any case, RFC 7235); none,
        or two (which one would count is ambiguous), is refused."""
        if self._token is None or path.startswith(HEALTH_PREFIX):
            return True
        given = [value for key, value in (metadata or ()) if key == "authorization"]
        if len(given) != 1:
            return False
        value = given[0].encode() if isinstance(given[0], str) else bytes(given[0])
        scheme, _, token = value.partition(b" ")
        return scheme.lower() == b"bearer" and hmac.compare_digest(token, self._token)

    def _run(self, path: str, authorized: bool, handler: grpc.RpcMethodHandler):
        """The wrapped call: a coroutine (request_iterator, context) -> the handler's answer."""
        method = path.rsplit("/", 1)[-1]
        logged = path.startswith(self.logged_prefix)
        limited = path in self.limited_methods
        unary_request = not handler.request_streaming
        inner = _behavior(handler)
        deserializer = handler.request_deserializer

        async def run(request_iterator, context, respond):
            start = time.perf_counter()
            code = grpc.StatusCode.OK
            fields: dict[str, Any] = {}
            token = _CALL_FIELDS.set(fields)
            admitted = quiet = False  # quiet: logged by a rate-limited warning instead
            reserved = 0
            self.metrics.in_flight.labels(method).inc()
            try:
                if not authorized:
                    code, quiet = grpc.StatusCode.UNAUTHENTICATED, True
                    self.warnings.warning("unauthenticated", "unauthenticated call refused",
                                          {"method": method, "peer": context.peer()})  # fmt: skip
                    await context.abort(code, "missing or invalid bearer token")
                if unary_request:
                    if limited:
                        raw = await self._upload(request_iterator, context, method)
                        refused, quiet = await self._admit(context, method, len(raw))
                        if refused:
                            await context.abort(grpc.StatusCode.RESOURCE_EXHAUSTED, refused)
                        admitted, reserved = True, len(raw) * MESSAGE_COST
                    else:
                        raw = await self._receive(request_iterator, context, method)
                    request = _parse(deserializer, raw)
                    del raw
                    if isinstance(request, _Malformed):  # a value, not raised: no traceback
                        code, quiet = grpc.StatusCode.INVALID_ARGUMENT, True
                        self._malformed(method, context, request)
                        await context.abort(code, str(request))
                else:
                    request = _checked(request_iterator, deserializer)
                return await respond(inner, request, context)
            except _Rejected as rejected:
                code = rejected.code
                return None  # the call is over; gRPC raises its abort for us
            except grpc.aio.AbortError:
                code = _code(context)
                raise
            except _Malformed as malformed:
                code, quiet = grpc.StatusCode.INVALID_ARGUMENT, True
                self._malformed(method, context, malformed)
                await context.abort(code, str(malformed))
            except asyncio.CancelledError:
                code, quiet = grpc.StatusCode.CANCELLED, True
                self.warnings.warning(
                    "cancelled", "call cancelled by the client or its deadline",
                    {"method": method, "peer": context.peer()},
                )  # fmt: skip
                raise
            except Exception as error:
                if context.cancelled() or context.done():
                    # The client went away while the call ran: its mistake, not a fault.
                    code, quiet = grpc.StatusCode.CANCELLED, True
                    self.warnings.warning(
                        "cancelled", "call ended by the client while it ran",
                        {"method": method, "peer": context.peer(),
                         "error": type(error).__name__},
                    )  # fmt: skip
                    return None
                code = grpc.StatusCode.INTERNAL
                log.exception("%s failed", method, extra={"fields": {"method": method}})
                await context.abort(code, "internal error")
            finally:
                seconds = time.perf_counter() - start
                version = self.model_version()
                self.metrics.observe(method, code, seconds, version)
                self.metrics.in_flight.labels(method).dec()
                if admitted:
                    self.in_flight -= 1
                if reserved:
                    await self.budget.release(reserved)
                if logged and not quiet:
                    log.info(method, extra={"fields": {**fields, "code": code.name,
                                                       "seconds": round(seconds, 4),
                                                       "model_version": version}})  # fmt: skip
                _CALL_FIELDS.reset(token)

        return run

    async def _upload(self, request_iterator, context, method: str) -> bytes:
        """A limited call's message, received within the peer's cap on uploads in progress."""
        peer = context.peer()
        cap = self.settings.max_uploads_per_peer
        if self.uploading.get(peer, 0) >= cap:
            self.warnings.warning("too many uploads", "peer over its cap on uploads in progress",
                                  {"method": method, "peer": peer, "cap": cap})  # fmt: skip
            await context.abort(
                grpc.StatusCode.RESOURCE_EXHAUSTED,
                f"this connection has {cap} labeling requests still uploading, the limit per "
                "connection; finish sending them first",
            )
        self.uploading[peer] = self.uploading.get(peer, 0) + 1
        try:
            return await self._receive(request_iterator, context, method)
        finally:
            self.uploading[peer] -= 1
            if not self.uploading[peer]:
                del self.uploading[peer]

    async def _admit(self, context, method: str, size: int) -> tuple[str, bool]:
        """Take a slot and reserve the call's bytes: ("", False); or (why not, naming the
        limit, for RESOURCE_EXHAUSTED; whether a client warning logged it)."""
        settings = self.settings
        if self.in_flight >= settings.max_concurrent_rpcs:
            return (f"server busy: {self.in_flight} labeling calls in flight, the limit is "
                    f"{settings.max_concurrent_rpcs}; retry with backoff"), False  # fmt: skip
        self.in_flight += 1
        cost = size * MESSAGE_COST
        if not await self.budget.reserve(cost, settings.budget_wait_s):
            self.in_flight -= 1
            limit_mb = settings.max_inflight_bytes / 2**20
            if cost > settings.max_inflight_bytes:
                message = (f"request: a {size / 2**20:.1f} MB message needs {cost / 2**20:.0f} MB "
                           f"of the server's {limit_mb:.0f} MB budget for frames in flight, more "
                           "than all of it; send fewer points or a smaller image")  # fmt: skip
            else:
                message = (f"server busy: frames in flight hold {self.budget.used / 2**20:.0f} MB "
                           f"of the {limit_mb:.0f} MB budget and this one needs "
                           f"{cost / 2**20:.0f} MB more; retry with backoff")  # fmt: skip
            self.warnings.warning(
                "over the byte budget", "call refused by the byte budget",
                {"method": method, "peer": context.peer(), "bytes": size},
            )  # fmt: skip
            return message, True
        return "", False

    async def _receive(self, request_iterator, context, method: str) -> bytes:
        """The call's one request message (raw bytes); _Rejected, or an abort when none
        arrives in time."""
        try:
            raw = await asyncio.wait_for(anext(request_iterator), self.settings.receive_timeout_s)
        except StopAsyncIteration:
            try:
                await context.abort(grpc.StatusCode.INVALID_ARGUMENT, "request: no message sent")
            except grpc.aio.AbortError:
                raise
            except grpc.aio.InternalError:
                # gRPC had finished the call already: it refused an over-size message.
                raise _Rejected(grpc.StatusCode.RESOURCE_EXHAUSTED) from None
        except asyncio.TimeoutError:
            fields = {"method": method, "peer": context.peer(),
                      "receive_timeout_s": self.settings.receive_timeout_s}  # fmt: skip
            self.warnings.warning("slow client", "request message not received in time", fields)
            await context.abort(
                grpc.StatusCode.DEADLINE_EXCEEDED,
                f"request: the message did not arrive within {self.settings.receive_timeout_s} s",
            )
        return raw

    def _malformed(self, method: str, context, malformed: _Malformed) -> None:
        self.warnings.warning(
            "malformed request", "request bytes are not the method's message",
            {"method": method, "peer": context.peer(), "bytes": malformed.size,
             "error": malformed.reason},
        )  # fmt: skip


class _Malformed(Exception):
    """Bytes that do not parse as the method's request message."""

    def __init__(self, size: int, reason: str) -> None:
        super().__init__(
            f"request: {size} bytes that are not a valid request message ({reason}); send the "
            "method's protobuf message"
        )
        self.size = size
        self.reason = reason


def _parse(deserializer, raw: bytes):
    """The message, or a _Malformed (returned, not raised) when raw is not one."""
    if deserializer is None:
        return raw
    try:
        return deserializer(raw)
    except Exception as error:  # noqa: BLE001 - any parse failure of client bytes is bad input
        return _Malformed(len(raw), f"{type(error).__name__}: {str(error)[:120]}")


async def _checked(request_iterator, deserializer):
    """A streaming request's messages, each parsed (the handler gets raw bytes)."""
    async for raw in request_iterator:
        message = _parse(deserializer, raw)
        if isinstance(message, _Malformed):
            raise message
        yield message


def _code(context) -> grpc.StatusCode:
    code = context.code()
    return code if isinstance(code, grpc.StatusCode) else grpc.StatusCode.UNKNOWN


def _behavior(handler: grpc.RpcMethodHandler):
    for name in ("unary_unary", "unary_stream", "stream_unary", "stream_stream"):
        behavior = getattr(handler, name)
        if behavior is not None:
            if not (inspect.iscoroutinefunction(behavior) or inspect.isasyncgenfunction(behavior)):
                raise TypeError(f"the edge serves asyncio handlers only, {behavior} is not one")
            return behavior
    raise TypeError(f"{handler} has no behavior")


async def _respond_unary(inner, request, context):
    return await inner(request, context)


async def _respond_stream(inner, request, context):
    answer = inner(request, context)
    if inspect.isasyncgen(answer):
        async for response in answer:
            await context.write(response)
    else:
        await answer


def _wrap(handler: grpc.RpcMethodHandler, run) -> grpc.RpcMethodHandler:
    """A stream-request handler (raw bytes in: `run` parses them) answering like handler."""
    serializer = handler.response_serializer
    if handler.response_streaming:

        async def streaming(request_iterator, context):
            await run(request_iterator, context, _respond_stream)

        return grpc.stream_stream_rpc_method_handler(streaming, None, serializer)

    async def unary(request_iterator, context):
        return await run(request_iterator, context, _respond_unary)

    return grpc.stream_unary_rpc_method_handler(unary, None, serializer)
