import pika, sys, time, subprocess
t0 = time.monotonic()
p = subprocess.Popen(sys.argv[2:], stdout=open("/tmp/st/restart.log","w"), stderr=subprocess.STDOUT)
while True:
    try:
        c = pika.BlockingConnection(pika.URLParameters(sys.argv[1]))
        ch = c.channel()
        q = ch.queue_declare("perf-0", durable=True, passive=True) if False else None
        break
    except Exception:
        time.sleep(0.01)
t1 = time.monotonic()
print(f"accepting connections after {t1-t0:.2f} s")
c.close(); p.terminate(); p.wait()
