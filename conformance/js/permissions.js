'use strict';
// Permissions table driver, amqplib: node permissions.js --table FILE --url amqp://HOST:PORT
// Runs each step of conformance/permissions/table.json on a fresh connection
// and channel, printing {"name", "outcome"} per line: "ok" or "<code> <text>".
const fs = require('fs');
const amqp = require('amqplib');

const PASSWORDS = { guest: 'guest', pu: 'robot-pw' };

function arg(name) {
  const i = process.argv.indexOf(name);
  if (i < 0) throw new Error(`missing ${name}`);
  return process.argv[i + 1];
}

// amqplib's errors end with: <code> (<NAME>) with message "<reply text>";
// basic.get rejects with the channel.close frame itself; a refused
// connection.open keeps no text ("Expected ConnectionOpenOk; got
// <ConnectionClose channel:0>"), the same for any broker.
function reply(error) {
  if (error && error.fields && error.fields.replyCode) {
    return `${error.fields.replyCode} ${error.fields.replyText}`;
  }
  const found = /(\d{3}) \([A-Z-]+\) with message "(.*)"$/s.exec(String(error.message));
  return found ? `${found[1]} ${found[2]}` : `error ${error.message}`;
}

async function runStep(base, step) {
  const user = step.as || 'pu';
  const vhost = encodeURIComponent(step.vhost || '/');
  let connection;
  try {
    connection = await amqp.connect(`amqp://${user}:${PASSWORDS[user]}@${base}/${vhost}`);
  } catch (e) {
    return reply(e);
  }
  connection.on('error', () => {});
  try {
    const ch = await connection.createChannel();
    ch.on('error', () => {});
    // pika's defaults (not durable), so both drivers' steps mean the same.
    const args = { durable: false, arguments: step.arguments };
    switch (step.op) {
      case 'connection.open': break;
      case 'queue.declare':
        if (step.passive) await ch.checkQueue(step.queue);
        else await ch.assertQueue(step.queue, args);
        break;
      case 'queue.delete': await ch.deleteQueue(step.queue); break;
      case 'queue.purge': await ch.purgeQueue(step.queue); break;
      case 'queue.bind': await ch.bindQueue(step.queue, step.exchange, step.routing_key); break;
      case 'queue.unbind': await ch.unbindQueue(step.queue, step.exchange, step.routing_key); break;
      case 'exchange.declare':
        if (step.passive) await ch.checkExchange(step.exchange);
        else await ch.assertExchange(step.exchange, step.type, args);
        break;
      case 'exchange.delete': await ch.deleteExchange(step.exchange); break;
      case 'exchange.bind': await ch.bindExchange(step.destination, step.source, step.routing_key); break;
      case 'exchange.unbind': await ch.unbindExchange(step.destination, step.source, step.routing_key); break;
      case 'basic.publish': ch.publish(step.exchange, step.routing_key, Buffer.from('permissions')); break;
      case 'basic.consume': await ch.consume(step.queue, () => {}); break;
      case 'basic.get': await ch.get(step.queue, { noAck: true }); break;
      default: throw new Error(`unknown op ${step.op}`);
    }
    // A round trip, so that a refused publish has closed the channel.
    await ch.prefetch(1);
    return 'ok';
  } catch (e) {
    return reply(e);
  } finally {
    await connection.close().catch(() => {});
  }
}

async function main() {
  const table = JSON.parse(fs.readFileSync(arg('--table'), 'utf8'));
  const base = new URL(arg('--url')).host;
  for (const step of table.steps) {
    console.log(JSON.stringify({ name: step.name, outcome: await runStep(base, step) }));
  }
}

main().then(() => process.exit(0), (e) => { console.error(e); process.exit(1); });
