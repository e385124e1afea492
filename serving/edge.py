"""The server's edge: one `grpc.aio` interceptor every call passes, whatever its fate.

For each call it
- counts it (requests, errors, latency, in flight; `serving.metrics`) with the status code the
  client got, rejected calls included;
- checks the bearer token before reading anything (health is exempt);
- admits at most `max_concurrent_rpcs` calls of the labeling service at once and answers
  RESOURCE_EXHAUSTED beyond (health and reflection are exempt, so they always answer);
- receives the request message itself, with a time limit (a client that sends headers and
  part of a message, then nothing, is dropped with DEADLINE_EXCEEDED after
  `receive_timeout_s`; it never holds a thread, the server being asyncio);
- parses it itself: bytes that are not the method's message are INVALID_ARGUMENT (gRPC's own
  deserialisation would answer INTERNAL and log a traceback), logged as one WARNING line a
  few seconds at most.

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


@dataclass(frozen=True)
class EdgeSettings:
    token: str | None = None  # None: no authentication
    max_concurrent_rpcs: int = 64
    receive_timeout_s: float = 30.0
    warning_interval_s: float = 10.0

    def __post_init__(self) -> None:
        if self.token is not None and not self.token:
            raise ValueError("token: empty; give a token or None (authentication off)")
        if self.max_concurrent_rpcs < 1:
            raise ValueError(f"max_concurrent_rpcs must be >= 1, got {self.max_concurrent_rpcs}")
        if not self.receive_timeout_s > 0:
            raise ValueError(f"receive_timeout_s must be > 0, got {self.receive_timeout_s}")


class RateLimitedWarnings:
    """At most one WARNING line per kind every interval_s seconds; the next one says how many
    were left out."""

    def __init__(self, interval_s: float) -> None:
        self.interval_s = interval_s
        self._last: dict[str, float] = {}
        self._suppressed: dict[str, int] = {}

    def warning(self, kind: str, message: str, fields: dict[str, Any]) -> None:
        now = time.monotonic()
        if now - self._last.get(kind, -float("inf")) < self.interval_s:
            self._suppressed[kind] = self._suppressed.get(kind, 0) + 1
            return
        self._last[kind] = now
        suppressed = self._suppressed.pop(kind, 0)
        log.warning(message, extra={"fields": {**fields, "suppressed_since_last": suppressed}})


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
        limited_prefix: str,
    ) -> None:
        """limited_prefix: methods under it (the labeling service) are admission-limited and
        logged; model_version: the served version, for the metrics' label."""
        self.settings = settings
        self.metrics = metrics
        self.model_version = model_version
        self.limited_prefix = limited_prefix
        self.warnings = RateLimitedWarnings(settings.warning_interval_s)
        self.in_flight = 0
        self._token = None if settings.token is None else settings.token.encode()

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
        limited = path.startswith(self.limited_prefix)
        unary_request = not handler.request_streaming
        inner = _behavior(handler)
        deserializer = handler.request_deserializer

        async def run(request_iterator, context, respond):
            start = time.perf_counter()
            code = grpc.StatusCode.OK
            fields: dict[str, Any] = {}
            token = _CALL_FIELDS.set(fields)
            admitted = quiet = False  # quiet: logged by a rate-limited warning instead
            self.metrics.in_flight.labels(method).inc()
            try:
                if not authorized:
                    code, quiet = grpc.StatusCode.UNAUTHENTICATED, True
                    self.warnings.warning("unauthenticated", "unauthenticated call refused",
                                          {"method": method, "peer": context.peer()})  # fmt: skip
                    await context.abort(code, "missing or invalid bearer token")
                if limited:
                    if self.in_flight >= self.settings.max_concurrent_rpcs:
                        code = grpc.StatusCode.RESOURCE_EXHAUSTED
                        await context.abort(
                            code,
                            f"server busy: {self.in_flight} labeling calls in flight, the "
                            f"limit is {self.settings.max_concurrent_rpcs}; retry with backoff",
                        )
                    self.in_flight += 1
                    admitted = True
                if unary_request:
                    request = await self._receive(request_iterator, context, deserializer, method)
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
                code = grpc.StatusCode.CANCELLED
                raise
            except Exception:
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
                if limited and not quiet:
                    log.info(method, extra={"fields": {**fields, "code": code.name,
                                                       "seconds": round(seconds, 4),
                                                       "model_version": version}})  # fmt: skip
                _CALL_FIELDS.reset(token)

        return run

    async def _receive(self, request_iterator, context, deserializer, method: str):
        """The call's one request message, parsed; _Malformed, or _Rejected / an abort when
        none arrives in time."""
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
        return _parse(deserializer, raw)

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
