#!/usr/bin/env python3
"""Wrong-password flood against a leveret binary; samples RSS/threads; measures legit logins.
usage: flood.py BINARY PORT"""
import asyncio, os, struct, subprocess, sys, time, tempfile, random, statistics

BIN, PORT = sys.argv[1], int(sys.argv[2])
SOCKETS, DURATION = 100, 15.0
NUSERS = 12

def frame_method(cls, meth, payload):
    body = struct.pack(">HH", cls, meth) + payload
    return struct.pack(">BHI", 1, 0, len(body)) + body + b"\xce"

def shortstr(s): return bytes([len(s)]) + s
def longstr(s): return struct.pack(">I", len(s)) + s

def start_ok(user, pw):
    resp = b"\0" + user + b"\0" + pw
    return frame_method(10, 11, struct.pack(">I", 0) + shortstr(b"PLAIN") + longstr(resp) + shortstr(b"en_US"))

async def read_frame(r):
    hdr = await r.readexactly(7)
    t, ch, size = struct.unpack(">BHI", hdr)
    body = await r.readexactly(size + 1)
    return t, body[:-1]

async def attempt(user, pw, hang_after=None):
    """True if tune received (auth passed), False if refused/closed."""
    r, w = await asyncio.open_connection("127.0.0.1", PORT)
    try:
        w.write(b"AMQP\x00\x00\x09\x01")
        t, body = await read_frame(r)
        w.write(start_ok(user, pw)); await w.drain()
        if hang_after is not None:
            await asyncio.sleep(hang_after); return None
        while True:
            t, body = await read_frame(r)
            if t == 1:
                cls, meth = struct.unpack(">HH", body[:4])
                if (cls, meth) == (10, 30): return True
                if (cls, meth) == (10, 50): return False
    except (asyncio.IncompleteReadError, ConnectionError):
        return False
    finally:
        w.close()

def proc_figures(pid):
    rss = 0
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith("VmRSS:"): rss = int(line.split()[1]) // 1024
            if line.startswith("Threads:"): th = int(line.split()[1])
    return rss, th

async def main():
    d = tempfile.mkdtemp()
    cfg = os.path.join(d, "c.toml")
    with open(cfg, "w") as f:
        f.write('loopback-users = []\n')
        f.write('[[users]]\nname = "guest"\npassword = "guest"\ntags = ["administrator"]\n')
        f.write('[[users.permissions]]\nvhost = "/"\nconfigure = ".*"\nwrite = ".*"\nread = ".*"\n')
        for i in range(NUSERS):
            f.write(f'[[users]]\nname = "robot{i}"\npassword = "pw{i}"\n')
    p = subprocess.Popen([BIN, "--config", cfg, "--data-dir", os.path.join(d, "data"),
        "--listen", f"127.0.0.1:{PORT}", "--http-listen", f"127.0.0.1:{PORT+1}",
        "--metrics-listen", f"127.0.0.1:{PORT+2}", "--log", "error"], stderr=subprocess.DEVNULL)
    for _ in range(100):
        try:
            _, w = await asyncio.open_connection("127.0.0.1", PORT); w.close(); break
        except OSError: await asyncio.sleep(0.1)
    await asyncio.sleep(1)
    assert await attempt(b"guest", b"guest"), "guest login"
    idle = proc_figures(p.pid); print("idle rss MB, threads:", idle, flush=True)
    stop = time.monotonic() + DURATION
    attempts = 0; peak = [0, 0]
    async def flooder():
        nonlocal attempts
        while time.monotonic() < stop:
            hang = 0.03 if random.random() < 0.5 else None
            try:
                await asyncio.wait_for(attempt(b"guest", b"wrong%d" % random.randrange(1 << 30), hang), 12)
            except Exception: pass
            attempts += 1
    async def sampler():
        while time.monotonic() < stop + 1:
            rss, th = proc_figures(p.pid); peak[0] = max(peak[0], rss); peak[1] = max(peak[1], th)
            await asyncio.sleep(0.25)
    known, first = [], []
    async def legit():
        i = 0
        await asyncio.sleep(1)
        while time.monotonic() < stop - 1 and i < NUSERS:
            t = time.monotonic(); ok = await asyncio.wait_for(attempt(b"guest", b"guest"), 30)
            known.append((time.monotonic() - t, ok))
            t = time.monotonic(); ok = await asyncio.wait_for(attempt(b"robot%d" % i, b"pw%d" % i), 30)
            first.append((time.monotonic() - t, ok)); i += 1
            await asyncio.sleep(0.5)
    await asyncio.gather(sampler(), legit(), *[flooder() for _ in range(SOCKETS)])
    def fmt(xs):
        oks = sum(1 for _, ok in xs if ok)
        ts = sorted(1000 * t for t, _ in xs)
        return f"{oks}/{len(xs)} ok, ms min {ts[0]:.0f} median {statistics.median(ts):.0f} max {ts[-1]:.0f}" if ts else "none"
    print(f"attempts {attempts}; peak rss {peak[0]} MB threads {peak[1]}")
    print("known user (guest) logins:", fmt(known))
    print("first-time user logins:", fmt(first))
    for s in (1, 5):
        await asyncio.sleep(s if s == 1 else 4)
        print(f"after +{s}s: rss MB, threads:", proc_figures(p.pid), flush=True)
    p.terminate(); p.wait()

asyncio.run(main())
