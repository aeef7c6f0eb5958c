import pika, sys
url = sys.argv[1]; n = int(sys.argv[2])
c = pika.BlockingConnection(pika.URLParameters(url)); ch = c.channel()
ch.exchange_declare("st.x", "topic", durable=True)
for i in range(0, n):
    q = f"st.q{i % 1000}"
    if i < 1000:
        ch.queue_declare(q, durable=True)
    ch.queue_bind(q, "st.x", routing_key=f"k.{i}")
c.close()
