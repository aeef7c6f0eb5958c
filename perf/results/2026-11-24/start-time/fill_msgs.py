import pika, sys
url = sys.argv[1]; n = int(sys.argv[2])
c = pika.BlockingConnection(pika.URLParameters(url)); ch = c.channel()
ch.queue_declare("st.backlog", durable=True)
props = pika.BasicProperties(delivery_mode=2)
body = b"0123456789abcdef"
for i in range(n):
    ch.basic_publish("", "st.backlog", body, props)
ch.confirm_delivery()
ch.basic_publish("", "st.backlog", body, props)
print(ch.queue_declare("st.backlog", durable=True, passive=True).method.message_count)
c.close()
