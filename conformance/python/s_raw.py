"""Raw-frame scenarios: the protocol errors no well-behaved client library
will provoke (bad headers, frames on unopened channels, broken frame ends,
unexpected content frames, missed heartbeats), over a plain socket."""

import socket
import struct
import time

from harness import Failure, scenario

LIB = "raw"


def s(name):
    return scenario(LIB, name)


FRAME_END = b"\xce"


def shortstr(v):
    b = v.encode()
    return struct.pack("B", len(b)) + b


def longstr(v):
    b = v if isinstance(v, bytes) else v.encode()
    return struct.pack(">I", len(b)) + b


def table(d):
    out = b""
    for k, v in d.items():
        out += shortstr(k)
        if isinstance(v, bool):
            out += b"t" + struct.pack("B", v)
        elif isinstance(v, dict):
            out += b"F" + table(v)
        else:
            out += b"S" + longstr(str(v))
    return struct.pack(">I", len(out)) + out


def frame(ftype, channel, payload):
    return struct.pack(">BHI", ftype, channel, len(payload)) + payload + FRAME_END


def method(channel, cls, mth, args=b""):
    return frame(1, channel, struct.pack(">HH", cls, mth) + args)


class Raw:
    def __init__(self, t, timeout=5.0):
        self.sock = socket.create_connection((t.host, t.port), timeout=timeout)
        self.sock.settimeout(timeout)
        self.buf = b""
        t.defer(self.close)

    def close(self):
        try:
            self.sock.close()
        except OSError:
            pass

    def send(self, data):
        self.sock.sendall(data)

    def recv_exact(self, n):
        while len(self.buf) < n:
            chunk = self.sock.recv(65536)
            if not chunk:
                raise EOFError("socket closed")
            self.buf += chunk
        out, self.buf = self.buf[:n], self.buf[n:]
        return out

    def read_frame(self):
        hdr = self.recv_exact(7)
        ftype, ch, size = struct.unpack(">BHI", hdr)
        payload = self.recv_exact(size)
        end = self.recv_exact(1)
        if end != FRAME_END:
            raise Failure(f"bad frame end from broker: {end!r}")
        return ftype, ch, payload

    def read_method(self, skip_heartbeats=True):
        while True:
            ftype, ch, payload = self.read_frame()
            if ftype == 8 and skip_heartbeats:
                continue
            if ftype != 1:
                return ftype, ch, None, None, payload
            cls, mth = struct.unpack(">HH", payload[:4])
            return ftype, ch, cls, mth, payload[4:]

    def handshake(self, t, channel_max=0, frame_max=131072, heartbeat=0, open_channel=1):
        self.send(b"AMQP\x00\x00\x09\x01")
        _, _, cls, mth, _ = self.read_method()
        if (cls, mth) != (10, 10):
            raise Failure(f"expected connection.start, got {cls}.{mth}")
        props = table({"product": "leveret-conformance-raw",
                       "capabilities": {"authentication_failure_close": True, "consumer_cancel_notify": True}})
        resp = b"\x00" + t.user.encode() + b"\x00" + t.password.encode()
        self.send(method(0, 10, 11, props + shortstr("PLAIN") + longstr(resp) + shortstr("en_US")))
        _, _, cls, mth, args = self.read_method()
        if (cls, mth) != (10, 30):
            raise Failure(f"expected connection.tune, got {cls}.{mth}")
        s_chmax, s_fmax, s_hb = struct.unpack(">HIH", args[:8])
        self.tune = (s_chmax, s_fmax, s_hb)
        chmax = channel_max or s_chmax
        fmax = frame_max if frame_max else s_fmax
        self.frame_max = fmax
        self.send(method(0, 10, 31, struct.pack(">HIH", chmax, fmax, heartbeat)))
        self.send(method(0, 10, 40, shortstr(t.vhost) + shortstr("") + b"\x00"))
        _, _, cls, mth, _ = self.read_method()
        if (cls, mth) != (10, 41):
            raise Failure(f"expected connection.open-ok, got {cls}.{mth}")
        if open_channel:
            self.open_channel(open_channel)

    def open_channel(self, ch):
        self.send(method(ch, 20, 10, shortstr("")))
        _, c, cls, mth, _ = self.read_method()
        if (cls, mth) != (20, 11):
            raise Failure(f"expected channel.open-ok, got {cls}.{mth}")

    def expect_close(self, label, t, code, scope="connection"):
        """Read until connection.close (or channel.close); record and check the code."""
        want = (10, 50) if scope == "connection" else (20, 40)
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline:
            try:
                ftype, ch, cls, mth, args = self.read_method()
            except (EOFError, ConnectionResetError, socket.timeout) as e:
                t.obs(label, ["no close method", type(e).__name__])
                raise Failure(f"{label}: expected {scope}.close {code}, got {type(e).__name__}")
            if (cls, mth) == want:
                rc = struct.unpack(">H", args[:2])[0]
                tl = args[2]
                text = args[3 : 3 + tl].decode("utf-8", "replace")
                ccls, cmth = struct.unpack(">HH", args[3 + tl : 7 + tl])
                t.eq(label, [rc, text.split(" - ")[0]], [code, text.split(" - ")[0]])
                t.obs(label + " (failing method ids)", [ccls, cmth])
                if rc != code:
                    raise Failure(f"{label}: expected {code}, got {rc} {text!r}")
                if scope == "connection":
                    self.send(method(0, 10, 51))
                return rc
        raise Failure(f"{label}: no {scope}.close within 5s")

    def expect_eof(self, timeout=5.0):
        self.sock.settimeout(timeout)
        start = time.monotonic()
        try:
            while True:
                data = self.sock.recv(65536)
                if not data:
                    return time.monotonic() - start
        except ConnectionResetError:
            return time.monotonic() - start
        except socket.timeout:
            return None


def outcome(r, wait=1.0):
    """What the broker does next: a method, a closed socket, or nothing."""
    r.sock.settimeout(wait)
    try:
        ftype, ch, cls, mth, args = r.read_method()
        if (cls, mth) == (10, 50):
            return ["connection.close", struct.unpack(">H", args[:2])[0]]
        if (cls, mth) == (20, 40):
            return ["channel.close", struct.unpack(">H", args[:2])[0]]
        return ["method", ch, cls, mth]
    except (EOFError, ConnectionResetError):
        return ["eof"]
    except socket.timeout:
        return ["nothing"]


def queue_declare(ch, name, passive=False):
    bits = 1 if passive else 0
    return method(ch, 50, 10, struct.pack(">H", 0) + shortstr(name) + struct.pack("B", bits) + table({}))


def basic_publish(ch, exchange, key):
    return method(ch, 60, 40, struct.pack(">H", 0) + shortstr(exchange) + shortstr(key) + b"\x00")


def content_header(ch, size):
    return frame(2, ch, struct.pack(">HHQH", 60, 0, size, 0))


def body(ch, data):
    return frame(3, ch, data)


# protocol header ----------------------------------------------------------------


@s("header.unsupported_version")
def _(t):
    r = Raw(t)
    r.send(b"AMQP\x00\x00\x0a\x00")
    t.eq("broker answers with the header it speaks", r.recv_exact(8), b"AMQP\x00\x00\x09\x01")
    t.eq("then closes", r.expect_eof() is not None, True)


@s("header.not_amqp")
def _(t):
    r = Raw(t)
    r.send(b"GET / HTTP/1.1\r\nHost: x\r\n\r\n")
    t.eq("broker answers with the header it speaks", r.recv_exact(8), b"AMQP\x00\x00\x09\x01")
    t.eq("then closes", r.expect_eof() is not None, True)


@s("handshake.full_and_close")
def _(t):
    r = Raw(t)
    r.handshake(t)
    t.eq("tune proposes a frame_max >= 4096 and a heartbeat", [r.tune[1] >= 4096, r.tune[2] > 0], [True, True])
    r.send(method(0, 10, 50, struct.pack(">H", 200) + shortstr("bye") + struct.pack(">HH", 0, 0)))
    _, _, cls, mth, _ = r.read_method()
    t.eq("close-ok", [cls, mth], [10, 51])


@s("handshake.missing_heartbeats_close_connection")
def _(t):
    r = Raw(t, timeout=10)
    r.handshake(t, heartbeat=1, open_channel=0)
    # Say nothing: the broker must give up after about two missed heartbeats
    # (2-3 s). The bound is a hang limit, far below the 60 s a broker that
    # ignored the negotiated interval would take, and far above what a
    # loaded machine adds.
    limit = 20
    start = time.monotonic()
    r.sock.settimeout(limit)
    closed = False
    try:
        while time.monotonic() - start < limit:
            data = r.sock.recv(65536)
            if not data:
                closed = True
                break
    except (ConnectionResetError, socket.timeout):
        closed = time.monotonic() - start < limit
    waited = time.monotonic() - start
    t.eq("broker closed the silent connection", closed, True)
    t.check(waited < limit, f"closed after {waited:.1f}s, expected about 2-3s")


@s("channel.closes_and_reopens")
def _(t):
    r = Raw(t)
    r.handshake(t)
    r.send(method(1, 20, 40, struct.pack(">H", 200) + shortstr("done") + struct.pack(">HH", 0, 0)))
    _, ch, cls, mth, _ = r.read_method()
    t.eq("channel.close-ok", [ch, cls, mth], [1, 20, 41])
    r.open_channel(1)
    t.obs("reopened channel 1", True)


# error replies -------------------------------------------------------------------


@s("error.channel_not_open")
def _(t):
    r = Raw(t)
    r.handshake(t, open_channel=0)
    r.send(queue_declare(3, ""))
    r.expect_close("method on unopened channel", t, 504)


@s("error.channel_open_twice")
def _(t):
    r = Raw(t)
    r.handshake(t)
    r.send(method(1, 20, 10, shortstr("")))
    r.expect_close("second channel.open", t, 504)


@s("error.channel_above_channel_max")
def _(t):
    r = Raw(t)
    r.handshake(t, channel_max=10, open_channel=0)
    r.send(method(11, 20, 10, shortstr("")))
    # RabbitMQ 3.10 opens it anyway: recorded for --ref, not asserted.
    t.obs("answer to channel.open above the negotiated channel_max", outcome(r))


@s("error.bad_frame_end")
def _(t):
    r = Raw(t)
    r.handshake(t)
    bad = queue_declare(1, "")[:-1] + b"\x00"
    r.send(bad)
    r.expect_close("frame end not 0xCE", t, 501)


@s("error.unknown_frame_type")
def _(t):
    r = Raw(t)
    r.handshake(t)
    r.send(frame(9, 1, b"\x00\x00"))
    r.expect_close("frame type 9", t, 501)


@s("error.frame_larger_than_frame_max")
def _(t):
    r = Raw(t)
    r.handshake(t, frame_max=4096)
    r.send(basic_publish(1, "", "nowhere") + content_header(1, 10000) + body(1, b"x" * 9000))
    r.expect_close("body frame over frame_max", t, 501)


@s("error.content_header_without_method")
def _(t):
    r = Raw(t)
    r.handshake(t)
    r.send(content_header(1, 3))
    r.expect_close("header frame with no publish", t, 505)


@s("error.body_without_header")
def _(t):
    r = Raw(t)
    r.handshake(t)
    r.send(body(1, b"abc"))
    r.expect_close("body frame with no publish", t, 505)


@s("error.method_instead_of_content")
def _(t):
    r = Raw(t)
    r.handshake(t)
    r.send(basic_publish(1, "", "nowhere") + queue_declare(1, ""))
    r.expect_close("method where a content header was due", t, 505)


@s("error.body_longer_than_declared")
def _(t):
    r = Raw(t)
    r.handshake(t)
    r.send(basic_publish(1, "", "nowhere") + content_header(1, 3) + body(1, b"abcdef"))
    # RabbitMQ 3.10 says nothing within a second: recorded for --ref, not asserted.
    t.obs("answer to a body larger than declared", outcome(r))


@s("error.heartbeat_on_a_channel")
def _(t):
    r = Raw(t)
    r.handshake(t)
    r.send(frame(8, 1, b""))
    r.expect_close("heartbeat frame on channel 1", t, 505)


@s("error.unknown_method")
def _(t):
    r = Raw(t)
    r.handshake(t)
    r.send(method(1, 60, 999, b""))
    res = outcome(r, 5)
    t.obs("answer to an unknown method", res)
    t.check(res[0] in ("eof", "connection.close"), f"the connection must end, got {res}")


@s("error.connection_method_on_a_channel")
def _(t):
    r = Raw(t)
    r.handshake(t)
    r.send(method(1, 10, 40, shortstr("/") + shortstr("") + b"\x00"))
    r.expect_close("connection.open on channel 1", t, 503)


@s("error.channel_method_on_channel_zero")
def _(t):
    r = Raw(t)
    r.handshake(t)
    r.send(queue_declare(0, ""))
    r.expect_close("queue.declare on channel 0", t, 504)


@s("error.publish_then_channel_error_keeps_connection")
def _(t):
    r = Raw(t)
    r.handshake(t)
    r.send(basic_publish(1, t.n("no-exchange"), "k") + content_header(1, 1) + body(1, b"x"))
    r.expect_close("publish to missing exchange", t, 404, scope="channel")
    r.send(method(1, 20, 41))
    r.open_channel(2)
    t.obs("connection still usable", True)


@s("order.queue_delete_ok_before_consumer_cancel")
def _(t):
    """Deleting a queue on the channel that consumes from it: RabbitMQ
    answers queue.delete-ok first and sends basic.cancel after it, which
    py-amqp and kombu rely on (a cancel while waiting for delete-ok raises)."""
    r = Raw(t)
    r.handshake(t)
    q = t.n("raw-delcons")
    r.send(method(1, 50, 10, struct.pack(">H", 0) + shortstr(q) + b"\x00" + table({})))
    r.read_method()
    r.send(method(1, 60, 20, struct.pack(">H", 0) + shortstr(q) + shortstr("ctag-1") + b"\x00" + table({})))
    r.read_method()
    r.send(method(1, 50, 40, struct.pack(">H", 0) + shortstr(q) + b"\x00"))
    seen = []
    r.sock.settimeout(1)
    try:
        while len(seen) < 2:
            _, ch, cls, mth, args = r.read_method()
            seen.append({(50, 41): "queue.delete-ok", (60, 30): "basic.cancel"}.get((cls, mth), f"{cls}.{mth}"))
    except (socket.timeout, EOFError):
        pass
    t.eq("frames after queue.delete", seen, ["queue.delete-ok", "basic.cancel"])
