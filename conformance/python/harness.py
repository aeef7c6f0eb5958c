"""Scenario harness shared by the Python drivers (pika, aio-pika, kombu, raw).

A scenario is a function taking a `T` (test context). It drives a real
client library, records what the client observed with `t.obs(...)` /
`t.eq(...)`, and fails by raising. The driver prints one JSON line per
scenario; conformance/run compares the `obs` lists of two brokers.
"""

import asyncio
import inspect
import json
import sys
import time
import traceback
import urllib.parse

REGISTRY = {}  # lib -> [(name, fn)]


def scenario(lib, name):
    def register(fn):
        REGISTRY.setdefault(lib, []).append((f"{lib}.{name}", fn))
        return fn

    return register


class Failure(AssertionError):
    pass


def reply_name(text):
    """'NOT_FOUND - no queue ...' -> 'NOT_FOUND' (the constant RabbitMQ prefixes)."""
    if text is None:
        return None
    if isinstance(text, bytes):
        text = text.decode("utf-8", "replace")
    return str(text).split(" - ", 1)[0].strip()


def plain(value):
    """Make a value JSON-friendly and stable."""
    import datetime
    import decimal

    if isinstance(value, dict):
        return {str(k): plain(v) for k, v in sorted(value.items(), key=lambda kv: str(kv[0]))}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if isinstance(value, (bytes, bytearray, memoryview)):
        b = bytes(value)
        try:
            return {"bytes": b.decode("utf-8")}
        except UnicodeDecodeError:
            return {"hex": b.hex()}
    if isinstance(value, decimal.Decimal):
        return {"decimal": str(value)}
    if isinstance(value, datetime.datetime):
        return {"timestamp": int(value.replace(tzinfo=datetime.timezone.utc).timestamp()) if value.tzinfo is None else int(value.timestamp())}
    if isinstance(value, float):
        return value
    if value is None or isinstance(value, (bool, int, str)):
        return value
    return repr(value)


class T:
    def __init__(self, url, prefix, http=None):
        self.url = url
        self.prefix = prefix
        # The broker's management API (`--http`), for suites that change
        # policies or read listings as an operator would.
        self.http = http
        self.observations = []
        self._cleanups = []
        u = urllib.parse.urlparse(url)
        self.host = u.hostname or "127.0.0.1"
        self.port = u.port or 5672
        self.user = urllib.parse.unquote(u.username or "guest")
        self.password = urllib.parse.unquote(u.password or "guest")
        path = u.path[1:] if u.path.startswith("/") else u.path
        self.vhost = urllib.parse.unquote(path) if path else "/"

    # names -------------------------------------------------------------
    def n(self, name):
        """A name unique to this run (the runner strips the prefix when diffing)."""
        return f"{self.prefix}{name}"

    def url_with(self, user=None, password=None, vhost=None, query=None):
        user = self.user if user is None else user
        password = self.password if password is None else password
        vhost = self.vhost if vhost is None else vhost
        q = ("?" + query) if query else ""
        return "amqp://%s:%s@%s:%d/%s%s" % (
            urllib.parse.quote(user, safe=""),
            urllib.parse.quote(password, safe=""),
            self.host,
            self.port,
            urllib.parse.quote(vhost, safe=""),
            q,
        )

    # observations -----------------------------------------------------
    def obs(self, label, value=None):
        self.observations.append([label, plain(value)])
        return value

    def eq(self, label, actual, expected):
        self.obs(label, actual)
        if plain(actual) != plain(expected):
            raise Failure(f"{label}: expected {plain(expected)!r}, got {plain(actual)!r}")
        return actual

    def check(self, cond, message):
        if not cond:
            raise Failure(message)

    def defer(self, fn, *args, **kwargs):
        self._cleanups.append((fn, args, kwargs))

    def run_cleanups(self):
        for fn, args, kwargs in reversed(self._cleanups):
            try:
                r = fn(*args, **kwargs)
                if inspect.isawaitable(r):
                    asyncio.run(r) if not _loop_running() else None
            except Exception:
                pass
        self._cleanups.clear()


async def _run_async(fn, t):
    try:
        await asyncio.wait_for(fn(t), 60)
    finally:
        for cfn, args, kwargs in reversed(t._cleanups):
            try:
                r = cfn(*args, **kwargs)
                if inspect.isawaitable(r):
                    await asyncio.wait_for(r, 5)
            except BaseException:
                pass
        t._cleanups.clear()


def _loop_running():
    try:
        asyncio.get_running_loop()
        return True
    except RuntimeError:
        return False


# How long a scenario waits for something it expects: a hang limit, generous
# enough for a loaded CI machine (the wait ends as soon as the thing happens).
HANG = 30.0


def wait_until(pred, timeout=HANG, interval=0.02, what="condition"):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(interval)
    raise Failure(f"timed out after {timeout}s waiting for {what}")


def main(libs):
    import argparse

    ap = argparse.ArgumentParser()
    ap.add_argument("--url")
    ap.add_argument("--prefix", default="cf-")
    ap.add_argument("--only", default="")
    ap.add_argument("--http", help="the broker's management API, http://HOST:PORT")
    ap.add_argument("--list", action="store_true")
    args = ap.parse_args()

    scenarios = []
    for lib in libs:
        scenarios.extend(REGISTRY.get(lib, []))
    if args.list:
        for name, _ in scenarios:
            print(name)
        return 0
    only = set(filter(None, args.only.split(",")))
    for name, fn in scenarios:
        if only and name not in only:
            continue
        print(json.dumps({"start": name}), flush=True)
        t = T(args.url, args.prefix, args.http)
        started = time.monotonic()
        ok, error = True, None
        try:
            if inspect.iscoroutinefunction(fn):
                asyncio.run(_run_async(fn, t))
            else:
                fn(t)
        except Exception as e:  # noqa: BLE001 - a scenario failure of any kind
            ok = False
            tb = traceback.extract_tb(e.__traceback__)
            where = next((f"{fr.filename.rsplit('/', 1)[-1]}:{fr.lineno}" for fr in reversed(tb) if "/python/s_" in fr.filename), "")
            error = f"{type(e).__name__}: {e} {('at ' + where) if where else ''}".strip()
        finally:
            try:
                t.run_cleanups()
            except Exception:
                pass
        rec = {
            "name": name,
            "ok": ok,
            "error": error,
            "obs": t.observations,
            "ms": int((time.monotonic() - started) * 1000),
        }
        print(json.dumps(rec), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(0)
