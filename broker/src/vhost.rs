//! A virtual host: its exchanges and queues, declaring and deleting them
//! with RabbitMQ's checks, bindings between them, and routing a published
//! message to the set of queues it reaches. The registries are
//! `std::sync::RwLock<HashMap>`s: lookups take the read lock for one hash
//! probe, changes take the write lock briefly; neither is held across an
//! await or while a queue's own lock is taken.

use crate::channel::ReplyTarget;
use crate::error::{AmqpError, AmqpResult};
use crate::exchange::{Binding, Destination, Exchange, ExchangeKind, ExchangeOptions};
use crate::memory::MemoryGauge;
use crate::message::Message;
use crate::queue::{Deleted, Queue, QueueArgs, QueueOptions};
use crate::stats::BrokerCounters;
use crate::store::{BindingRecord, ExchangeRecord, Persistence, QueueRecord, StoreOp};
use leveret_protocol::{FieldTable, ShortStr};
use std::collections::HashMap;
use std::sync::{Arc, RwLock};

/// One virtual host.
#[derive(Debug)]
pub struct Vhost {
    /// Its name (`/` by default).
    pub name: ShortStr,
    exchanges: RwLock<HashMap<ShortStr, Arc<Exchange>>>,
    queues: RwLock<HashMap<ShortStr, Arc<Queue>>>,
    gauge: Arc<MemoryGauge>,
    persistence: Option<Arc<Persistence>>,
    counters: Arc<BrokerCounters>,
    /// Direct reply-to consumers by their reply name.
    reply_targets: RwLock<HashMap<ShortStr, ReplyTarget>>,
}

/// What queue.declare asked for.
#[derive(Debug, Clone)]
pub struct QueueDeclaration {
    /// Name (never empty here: the channel names server-named queues).
    pub name: ShortStr,
    /// Only check that it exists.
    pub passive: bool,
    /// The broker chose the name (`amq.gen-…`).
    pub server_named: bool,
    /// Properties.
    pub options: QueueOptions,
}

/// What exchange.declare asked for.
#[derive(Debug, Clone)]
pub struct ExchangeDeclaration {
    /// Name.
    pub name: ShortStr,
    /// Kind as named by the client.
    pub kind: ShortStr,
    /// Only check that it exists.
    pub passive: bool,
    /// Properties.
    pub options: ExchangeOptions,
}

fn read<T>(lock: &RwLock<T>) -> std::sync::RwLockReadGuard<'_, T> {
    lock.read().unwrap_or_else(|e| e.into_inner())
}

fn write<T>(lock: &RwLock<T>) -> std::sync::RwLockWriteGuard<'_, T> {
    lock.write().unwrap_or_else(|e| e.into_inner())
}

impl Vhost {
    /// A vhost with the default exchange and the predefined `amq.*` ones.
    pub fn new(
        name: ShortStr,
        gauge: Arc<MemoryGauge>,
        persistence: Option<Arc<Persistence>>,
        counters: Arc<BrokerCounters>,
    ) -> Arc<Self> {
        let vhost = Vhost {
            name,
            exchanges: RwLock::new(HashMap::new()),
            queues: RwLock::new(HashMap::new()),
            gauge,
            persistence,
            counters,
            reply_targets: RwLock::new(HashMap::new()),
        };
        let durable = ExchangeOptions {
            durable: true,
            ..Default::default()
        };
        for (name, kind) in [
            ("", ExchangeKind::Direct),
            ("amq.direct", ExchangeKind::Direct),
            ("amq.fanout", ExchangeKind::Fanout),
            ("amq.topic", ExchangeKind::Topic),
            ("amq.headers", ExchangeKind::Headers),
            ("amq.match", ExchangeKind::Headers),
        ] {
            let name = ShortStr::from_static(name);
            let exchange = Exchange::new(name.clone(), kind, durable.clone());
            write(&vhost.exchanges).insert(name, Arc::new(exchange));
        }
        Arc::new(vhost)
    }

    /// The exchange with this name.
    pub fn exchange(&self, name: &ShortStr) -> Option<Arc<Exchange>> {
        read(&self.exchanges).get(name).cloned()
    }

    /// The queue with this name.
    pub fn queue(&self, name: &ShortStr) -> Option<Arc<Queue>> {
        read(&self.queues).get(name).cloned()
    }

    /// Every queue (for sweeping and connection cleanup).
    pub fn queues(&self) -> Vec<Arc<Queue>> {
        read(&self.queues).values().cloned().collect()
    }

    /// Up to `limit` queues after the first `skip` in the registry's order
    /// (which holds while no queue is added or removed): one chunk of a
    /// listing, so that listing many queues never holds the registry for
    /// long.
    pub fn queues_chunk(&self, skip: usize, limit: usize) -> Vec<Arc<Queue>> {
        read(&self.queues)
            .values()
            .skip(skip)
            .take(limit)
            .cloned()
            .collect()
    }

    /// Every exchange (for listings).
    pub fn exchanges(&self) -> Vec<Arc<Exchange>> {
        read(&self.exchanges).values().cloned().collect()
    }

    /// The exchange, or 404 as RabbitMQ words it.
    pub fn exchange_or_404(&self, name: &ShortStr) -> AmqpResult<Arc<Exchange>> {
        self.exchange(name).ok_or_else(|| {
            AmqpError::not_found(format_args!(
                "no exchange '{}' in vhost '{}'",
                name, self.name
            ))
        })
    }

    /// The queue, or 404 as RabbitMQ words it.
    pub fn queue_or_404(&self, name: &ShortStr) -> AmqpResult<Arc<Queue>> {
        self.queue(name).ok_or_else(|| {
            AmqpError::not_found(format_args!("no queue '{}' in vhost '{}'", name, self.name))
        })
    }

    /// exchange.declare.
    pub fn declare_exchange(&self, decl: ExchangeDeclaration) -> AmqpResult<Arc<Exchange>> {
        if decl.name.is_empty() {
            // Even a passive declare of the default exchange is refused.
            return Err(default_exchange_refusal(&decl.name, &self.name));
        }
        if decl.passive {
            return self.exchange_or_404(&decl.name);
        }
        let Some(kind) = ExchangeKind::parse(decl.kind.as_bytes()) else {
            return Err(AmqpError::command_invalid(format_args!(
                "unknown exchange type '{}'",
                decl.kind
            )));
        };
        if self.exchange(&decl.name).is_none() && decl.name.as_bytes().starts_with(b"amq.") {
            return Err(AmqpError::access_refused(format_args!(
                "exchange name '{}' contains reserved prefix 'amq.*'",
                decl.name
            )));
        }
        if let Some(alternate) = decl.options.arguments.get("alternate-exchange") {
            if !matches!(alternate, leveret_protocol::FieldValue::LongStr(_)) {
                return Err(AmqpError::precondition_failed(format_args!(
                    "invalid arg 'alternate-exchange' for exchange '{}' in vhost '{}'",
                    decl.name, self.name
                )));
            }
        }
        let mut exchanges = write(&self.exchanges);
        if let Some(existing) = exchanges.get(&decl.name) {
            if existing.kind != kind
                || existing.options.durable != decl.options.durable
                || existing.options.auto_delete != decl.options.auto_delete
                || existing.options.internal != decl.options.internal
                || existing.options.arguments != decl.options.arguments
            {
                return Err(AmqpError::precondition_failed(format_args!(
                    "inequivalent arg '{}' for exchange '{}' in vhost '{}': received '{}' but current is '{}'",
                    if existing.kind != kind { "type" } else if existing.options.durable != decl.options.durable { "durable" } else if existing.options.auto_delete != decl.options.auto_delete { "auto_delete" } else if existing.options.internal != decl.options.internal { "internal" } else { "arguments" },
                    decl.name,
                    self.name,
                    kind.name(),
                    existing.kind.name()
                )));
            }
            return Ok(Arc::clone(existing));
        }
        let exchange = Arc::new(Exchange::new(decl.name.clone(), kind, decl.options));
        exchanges.insert(decl.name, Arc::clone(&exchange));
        drop(exchanges);
        if exchange.options.durable {
            self.persist(vec![StoreOp::PutExchange(ExchangeRecord {
                vhost: self.name.clone(),
                name: exchange.name.clone(),
                kind: ShortStr::from_static(kind.name()),
                auto_delete: exchange.options.auto_delete,
                internal: exchange.options.internal,
                arguments: exchange.options.arguments.clone(),
            })]);
        }
        Ok(exchange)
    }

    /// exchange.delete.
    pub fn delete_exchange(&self, name: &ShortStr, if_unused: bool) -> AmqpResult<()> {
        if name.is_empty() || name.as_bytes().starts_with(b"amq.") {
            return Err(default_exchange_refusal(name, &self.name));
        }
        let Some(exchange) = self.exchange(name) else {
            // Deleting what does not exist succeeds, as in RabbitMQ.
            return Ok(());
        };
        if if_unused && (exchange.has_bindings() || self.is_bound_destination(&exchange)) {
            return Err(AmqpError::precondition_failed(format_args!(
                "exchange '{}' in vhost '{}' in use",
                name, self.name
            )));
        }
        write(&self.exchanges).remove(name);
        self.forget_exchange(&exchange);
        Ok(())
    }

    fn is_bound_destination(&self, exchange: &Arc<Exchange>) -> bool {
        let probe = Destination::Exchange(Arc::clone(exchange));
        read(&self.exchanges).values().any(|e| {
            let mut found = false;
            e.for_each_destination(|d| found |= *d == probe);
            found
        })
    }

    /// queue.declare; returns the queue and whether it was created.
    pub fn declare_queue(
        self: &Arc<Self>,
        decl: QueueDeclaration,
        connection_id: u64,
    ) -> AmqpResult<(Arc<Queue>, bool)> {
        if let Some(existing) = self.queue(&decl.name) {
            check_exclusive(&existing, connection_id, &self.name)?;
            if !decl.passive {
                let o = &existing.options;
                let d = &decl.options;
                let mismatch = if o.durable != d.durable {
                    Some("durable")
                } else if o.exclusive_owner.is_some() != d.exclusive_owner.is_some() {
                    Some("exclusive")
                } else if o.auto_delete != d.auto_delete {
                    Some("auto_delete")
                } else {
                    first_argument_mismatch(&o.arguments, &d.arguments)
                };
                if let Some(what) = mismatch {
                    return Err(AmqpError::precondition_failed(format_args!(
                        "inequivalent arg '{}' for queue '{}' in vhost '{}'",
                        what, decl.name, self.name
                    )));
                }
            }
            existing.touch();
            return Ok((existing, false));
        }
        if decl.passive {
            return Err(AmqpError::not_found(format_args!(
                "no queue '{}' in vhost '{}'",
                decl.name, self.name
            )));
        }
        if !decl.server_named && decl.name.as_bytes().starts_with(b"amq.") {
            return Err(AmqpError::access_refused(format_args!(
                "queue name '{}' contains reserved prefix 'amq.*'",
                decl.name
            )));
        }
        let args = QueueArgs::parse(&decl.options.arguments, &decl.name, &self.name)?;
        let mut queues = write(&self.queues);
        if let Some(existing) = queues.get(&decl.name) {
            // Declared by another channel between our check and the lock.
            return Ok((Arc::clone(existing), false));
        }
        // Exclusive queues die with their connection, so they are never stored.
        let durable_store = match &self.persistence {
            Some(p) if decl.options.durable && decl.options.exclusive_owner.is_none() => {
                Some((Arc::clone(p), p.next_queue_id()))
            }
            _ => None,
        };
        if let Some((persistence, id)) = &durable_store {
            persistence.submit(vec![StoreOp::PutQueue(QueueRecord {
                vhost: self.name.clone(),
                name: decl.name.clone(),
                id: *id,
                auto_delete: decl.options.auto_delete,
                arguments: decl.options.arguments.clone(),
            })]);
        }
        let queue = Arc::new(Queue::new(
            decl.name.clone(),
            decl.options,
            args,
            Arc::downgrade(self),
            Arc::clone(&self.gauge),
            durable_store,
            Arc::clone(&self.counters),
        ));
        queues.insert(decl.name, Arc::clone(&queue));
        Ok((queue, true))
    }

    /// Deletes a queue: its bindings and messages go with it; its consumers
    /// come back in [`Deleted`], to be notified.
    pub fn delete_queue(&self, queue: &Arc<Queue>) -> Deleted {
        {
            let mut queues = write(&self.queues);
            match queues.get(&queue.name) {
                Some(current) if Arc::ptr_eq(current, queue) => {
                    queues.remove(&queue.name);
                }
                _ => return Deleted::default(),
            }
        }
        let mut ops = Vec::new();
        for exchange in self.unbind_everywhere(&Destination::Queue(Arc::clone(queue)), &mut ops) {
            self.auto_delete_exchange(&exchange);
        }
        if queue.store_id().is_some() {
            ops.push(StoreOp::DeleteQueue {
                vhost: self.name.clone(),
                name: queue.name.clone(),
            });
        }
        self.persist(ops);
        queue.delete()
    }

    /// Deletes an auto-delete exchange that has lost its last binding.
    fn auto_delete_exchange(&self, exchange: &Arc<Exchange>) {
        if exchange.options.auto_delete && !exchange.has_bindings() {
            let removed = {
                let mut exchanges = write(&self.exchanges);
                let current = exchanges
                    .get(&exchange.name)
                    .is_some_and(|e| Arc::ptr_eq(e, exchange));
                current && exchanges.remove(&exchange.name).is_some()
            };
            if removed {
                self.forget_exchange(exchange);
            }
        }
    }

    /// Removes a deleted exchange's bindings, in memory and on disk.
    fn forget_exchange(&self, exchange: &Arc<Exchange>) {
        let mut ops = Vec::new();
        for binding in exchange.bindings() {
            if let Some(record) = self.binding_record(exchange, &binding) {
                ops.push(StoreOp::DeleteBinding(record));
            }
        }
        for source in self.unbind_everywhere(&Destination::Exchange(Arc::clone(exchange)), &mut ops)
        {
            self.auto_delete_exchange(&source);
        }
        if exchange.options.durable {
            ops.push(StoreOp::DeleteExchange {
                vhost: self.name.clone(),
                name: exchange.name.clone(),
            });
        }
        self.persist(ops);
    }

    /// Removes every binding to `destination` from every exchange, adding
    /// the store ops for durable ones to `ops`; returns the exchanges that
    /// lost a binding (candidates for auto-delete).
    fn unbind_everywhere(
        &self,
        destination: &Destination,
        ops: &mut Vec<StoreOp>,
    ) -> Vec<Arc<Exchange>> {
        let exchanges: Vec<Arc<Exchange>> = read(&self.exchanges).values().cloned().collect();
        let mut touched = Vec::new();
        for exchange in exchanges {
            let removed = exchange.unbind_destination(destination);
            if removed.is_empty() {
                continue;
            }
            ops.extend(
                removed
                    .iter()
                    .filter_map(|b| self.binding_record(&exchange, b))
                    .map(StoreOp::DeleteBinding),
            );
            touched.push(exchange);
        }
        touched
    }

    fn persist(&self, ops: Vec<StoreOp>) {
        if let (Some(persistence), false) = (&self.persistence, ops.is_empty()) {
            persistence.submit(ops);
        }
    }

    /// The stored form of a binding, if both its ends are durable.
    fn binding_record(&self, source: &Exchange, binding: &Binding) -> Option<BindingRecord> {
        if !source.options.durable {
            return None;
        }
        let (to_queue, destination) = match &binding.destination {
            Destination::Queue(q) => {
                q.store_id()?;
                (true, q.name.clone())
            }
            Destination::Exchange(e) if e.options.durable => (false, e.name.clone()),
            Destination::Exchange(_) => return None,
        };
        Some(BindingRecord {
            vhost: self.name.clone(),
            source: source.name.clone(),
            to_queue,
            destination,
            routing_key: binding.routing_key.clone(),
            arguments: binding.arguments.clone(),
        })
    }

    /// Adds a binding in memory and, between durable ends, on disk.
    fn add_binding(&self, source: &Exchange, binding: Binding) {
        if let Some(record) = self.binding_record(source, &binding) {
            self.persist(vec![StoreOp::PutBinding(record)]);
        }
        source.bind(binding);
    }

    /// Removes a binding; true if it existed.
    fn remove_binding(&self, source: &Exchange, binding: &Binding) -> bool {
        let removed = source.unbind(binding);
        if removed {
            if let Some(record) = self.binding_record(source, binding) {
                self.persist(vec![StoreOp::DeleteBinding(record)]);
            }
        }
        removed
    }

    /// queue.bind, and with `bind` false queue.unbind (unbinding what was
    /// never bound succeeds, as in RabbitMQ).
    pub fn bind_queue(
        &self,
        queue: &Arc<Queue>,
        exchange: &ShortStr,
        routing_key: ShortStr,
        arguments: FieldTable,
        bind: bool,
    ) -> AmqpResult<()> {
        let source = self.bindable_source(exchange)?;
        let binding = Binding {
            destination: Destination::Queue(Arc::clone(queue)),
            routing_key,
            arguments,
        };
        if bind {
            check_headers_binding(&source, &binding.arguments)?;
            self.add_binding(&source, binding);
        } else if self.remove_binding(&source, &binding) {
            self.auto_delete_exchange(&source);
        }
        Ok(())
    }

    /// exchange.bind and exchange.unbind.
    pub fn bind_exchange(
        &self,
        destination: &ShortStr,
        source: &ShortStr,
        routing_key: ShortStr,
        arguments: FieldTable,
        bind: bool,
    ) -> AmqpResult<()> {
        let missing_end = self.exchange(destination).is_none() || self.exchange(source).is_none();
        if !bind && missing_end {
            // Unbinding from or to a missing exchange succeeds, as in RabbitMQ.
            return Ok(());
        }
        let target = self.exchange_or_404(destination)?;
        if destination.is_empty() {
            return Err(default_exchange_refusal(destination, &self.name));
        }
        let from = self.bindable_source(source)?;
        let binding = Binding {
            destination: Destination::Exchange(target),
            routing_key,
            arguments,
        };
        if bind {
            check_headers_binding(&from, &binding.arguments)?;
            self.add_binding(&from, binding);
        } else if self.remove_binding(&from, &binding) {
            self.auto_delete_exchange(&from);
        }
        Ok(())
    }

    fn bindable_source(&self, exchange: &ShortStr) -> AmqpResult<Arc<Exchange>> {
        if exchange.is_empty() {
            return Err(default_exchange_refusal(exchange, &self.name));
        }
        self.exchange_or_404(exchange)
    }

    /// Collects in `queues` every queue a message published to `exchange`
    /// reaches, following exchange-to-exchange bindings and alternate
    /// exchanges, each queue once. `queues` is a buffer the caller reuses.
    pub fn route(
        &self,
        exchange: &Arc<Exchange>,
        routing_key: &ShortStr,
        headers: Option<&FieldTable>,
        queues: &mut Vec<Arc<Queue>>,
    ) {
        queues.clear();
        if exchange.name.is_empty() {
            if let Some(queue) = self.queue(routing_key) {
                queues.push(queue);
            }
            return;
        }
        let mut next: Vec<Arc<Exchange>> = Vec::new();
        let mut collect = |destination: &Destination| match destination {
            Destination::Queue(q) => queues.push(Arc::clone(q)),
            Destination::Exchange(e) => next.push(Arc::clone(e)),
        };
        exchange.route(routing_key, headers, &mut collect);
        if !next.is_empty() {
            // Exchange-to-exchange bindings: walk them once each, so a
            // cycle of bindings ends.
            let mut visited: Vec<Arc<Exchange>> = vec![Arc::clone(exchange)];
            while let Some(following) = next.pop() {
                if visited.iter().any(|v| Arc::ptr_eq(v, &following)) {
                    continue;
                }
                following.route(routing_key, headers, |destination| match destination {
                    Destination::Queue(q) => queues.push(Arc::clone(q)),
                    Destination::Exchange(e) => next.push(Arc::clone(e)),
                });
                visited.push(following);
            }
        }
        if queues.is_empty() {
            // Alternate exchanges, followed until one routes or a cycle.
            let mut alternate = exchange.alternate();
            let mut tried = vec![exchange.name.clone()];
            while let Some(name) = alternate.take() {
                if tried.contains(&name) {
                    break;
                }
                let Some(ae) = self.exchange(&name) else {
                    break;
                };
                ae.route(routing_key, headers, |destination| {
                    if let Destination::Queue(q) = destination {
                        queues.push(Arc::clone(q));
                    }
                });
                if queues.is_empty() {
                    alternate = ae.alternate();
                    tried.push(name);
                }
            }
        }
        if queues.len() > 1 {
            queues.sort_by_key(|q| Arc::as_ptr(q) as usize);
            queues.dedup_by(|a, b| Arc::ptr_eq(a, b));
        }
    }

    /// Publishes a message the broker made itself (dead letters).
    pub fn publish_internal(&self, exchange: &ShortStr, message: Arc<Message>) {
        let Some(exchange) = self.exchange(exchange) else {
            tracing::debug!(exchange = %exchange, "dead-letter exchange missing; message dropped");
            return;
        };
        let headers = leveret_protocol::BasicProperties::decode(&message.properties)
            .ok()
            .and_then(|p| p.headers);
        let mut queues = Vec::new();
        self.route(
            &exchange,
            &message.routing_key,
            headers.as_ref(),
            &mut queues,
        );
        for queue in &queues {
            queue.publish(Arc::clone(&message));
        }
    }

    /// Re-creates a stored exchange at start.
    pub fn restore_exchange(&self, record: &ExchangeRecord) {
        let Some(kind) = ExchangeKind::parse(record.kind.as_bytes()) else {
            tracing::warn!(exchange = %record.name, kind = %record.kind, "stored exchange of unknown kind skipped");
            return;
        };
        let options = ExchangeOptions {
            durable: true,
            auto_delete: record.auto_delete,
            internal: record.internal,
            arguments: record.arguments.clone(),
        };
        let exchange = Exchange::new(record.name.clone(), kind, options);
        write(&self.exchanges).insert(record.name.clone(), Arc::new(exchange));
    }

    /// Re-creates a stored queue at start (its messages are restored by the caller).
    pub fn restore_queue(self: &Arc<Self>, record: &QueueRecord) -> Option<Arc<Queue>> {
        let options = QueueOptions {
            durable: true,
            exclusive_owner: None,
            auto_delete: record.auto_delete,
            arguments: record.arguments.clone(),
        };
        let args = match QueueArgs::parse(&options.arguments, &record.name, &self.name) {
            Ok(args) => args,
            Err(e) => {
                tracing::warn!(queue = %record.name, error = %e, "stored queue arguments no longer valid; using none");
                QueueArgs::default()
            }
        };
        let persistence = Arc::clone(self.persistence.as_ref()?);
        let queue = Arc::new(Queue::new(
            record.name.clone(),
            options,
            args,
            Arc::downgrade(self),
            Arc::clone(&self.gauge),
            Some((persistence, record.id)),
            Arc::clone(&self.counters),
        ));
        write(&self.queues).insert(record.name.clone(), Arc::clone(&queue));
        Some(queue)
    }

    /// Re-creates a stored binding at start; false if an end is missing.
    pub fn restore_binding(&self, record: &BindingRecord) -> bool {
        let Some(source) = self.exchange(&record.source) else {
            return false;
        };
        let destination = if record.to_queue {
            self.queue(&record.destination).map(Destination::Queue)
        } else {
            self.exchange(&record.destination)
                .map(Destination::Exchange)
        };
        let Some(destination) = destination else {
            return false;
        };
        source.bind(Binding {
            destination,
            routing_key: record.routing_key.clone(),
            arguments: record.arguments.clone(),
        });
        true
    }

    /// Registers a direct reply-to consumer under its reply name.
    pub(crate) fn register_reply_target(&self, name: ShortStr, target: ReplyTarget) {
        write(&self.reply_targets).insert(name, target);
    }

    /// Removes a direct reply-to consumer.
    pub(crate) fn unregister_reply_target(&self, name: &ShortStr) {
        write(&self.reply_targets).remove(name);
    }

    /// The direct reply-to consumer with this reply name.
    pub(crate) fn reply_target(&self, name: &ShortStr) -> Option<ReplyTarget> {
        read(&self.reply_targets).get(name).cloned()
    }

    /// Deletes the exclusive queues of a closed connection.
    pub fn drop_exclusive(&self, connection_id: u64) {
        let owned: Vec<Arc<Queue>> = read(&self.queues)
            .values()
            .filter(|q| q.options.exclusive_owner == Some(connection_id))
            .cloned()
            .collect();
        for queue in owned {
            self.delete_queue(&queue).notify();
        }
    }

    /// Periodic housekeeping: expires messages past their TTL and deletes
    /// queues past x-expires.
    pub fn sweep(&self) {
        for queue in self.queues() {
            queue.expire();
            if queue.unused_expired() {
                tracing::debug!(queue = %queue.name, "queue expired (x-expires)");
                self.delete_queue(&queue).notify();
            }
        }
    }
}

fn default_exchange_refusal(name: &ShortStr, vhost: &ShortStr) -> AmqpError {
    AmqpError::access_refused(format_args!(
        "operation not permitted on the default exchange '{}' in vhost '{}'",
        name, vhost
    ))
}

fn check_headers_binding(exchange: &Exchange, arguments: &FieldTable) -> AmqpResult<()> {
    if exchange.kind == ExchangeKind::Headers && !crate::exchange::valid_x_match(arguments) {
        return Err(AmqpError::precondition_failed(
            "invalid x-match field value; expected all, any, all-with-x, or any-with-x",
        ));
    }
    Ok(())
}

/// Exclusive queues belong to one connection: 405 for any other.
pub fn check_exclusive(queue: &Queue, connection_id: u64, vhost: &ShortStr) -> AmqpResult<()> {
    match queue.options.exclusive_owner {
        Some(owner) if owner != connection_id => Err(AmqpError::resource_locked(format_args!(
            "cannot obtain exclusive access to locked queue '{}' in vhost '{}'. It could be originally declared on another connection or the exclusive property value does not match that of the original declaration.",
            queue.name, vhost
        ))),
        _ => Ok(()),
    }
}

/// RabbitMQ compares the arguments it validates; the first that differs.
fn first_argument_mismatch(current: &FieldTable, requested: &FieldTable) -> Option<&'static str> {
    const CHECKED: [&str; 9] = [
        "x-message-ttl",
        "x-expires",
        "x-max-length",
        "x-max-length-bytes",
        "x-overflow",
        "x-dead-letter-exchange",
        "x-dead-letter-routing-key",
        "x-max-priority",
        "x-queue-type",
    ];
    CHECKED
        .into_iter()
        .find(|key| current.get(key) != requested.get(key))
}
