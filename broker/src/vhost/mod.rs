//! A virtual host: its exchanges and queues, declaring and deleting them
//! with RabbitMQ's checks, and the bindings between them (routing a
//! published message is `routing`'s; storing it and offering it to the
//! queues it reached is `publish`'s, the one owner of a message's durable
//! write). The registries are
//! `std::sync::RwLock<HashMap>`s: lookups take the read lock for one hash
//! probe, changes take the write lock briefly; neither is held across an
//! await or while a queue's own lock is taken. The dead letters queue
//! operations return are routed here too (`Vhost::dead_letter`, see
//! `deadletter`). A vhost uses exchanges, queues and the consumer layer's
//! reply-to targets, never a channel.
//! Binding changes go through one [`BindingRegistry`] behind a mutex,
//! taken before the registries' locks and any exchange's; deleting a queue
//! or an exchange removes its bindings in steps of [`UNBIND_STEP`] with a
//! yield between steps.

use crate::alarm::memory::MemoryGauge;
use crate::arguments;
use crate::error::{AmqpError, AmqpResult};
use crate::exchange::{
    consistent_hash, Binding, BindingRegistry, Destination, Exchange, ExchangeKind, ExchangeOptions,
};
use crate::policy::{ObjectKind, VhostPolicies};
use crate::queue::{
    DeadLetters, Deleted, Queue, QueueArgs, QueueOptions, ReplyTarget, Stream, StreamArgs,
};
use crate::slice::{yield_if_spent, Progress, Slice};
use crate::stats::BrokerCounters;
use crate::store::{BindingRecord, ExchangeRecord, Persistence, QueueRecord, StoreOp};
use leveret_protocol::{FieldTable, ShortStr};
use std::collections::HashMap;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, RwLock};
use std::time::Instant;

/// Most bindings removed in one step when a queue or an exchange is
/// deleted; a deletion with more yields between steps.
const UNBIND_STEP: usize = 256;

/// One virtual host.
#[derive(Debug)]
pub struct Vhost {
    /// Its name (`/` by default).
    pub name: ShortStr,
    exchanges: RwLock<HashMap<ShortStr, Arc<Exchange>>>,
    queues: RwLock<HashMap<ShortStr, Arc<Queue>>>,
    /// Changes to `queues` so far, counted under its write lock: a lookup
    /// remembered with this count is still right while it is unchanged
    /// ([`Vhost::queue_remembered`]).
    queue_changes: AtomicU64,
    /// Every binding; held while a binding changes, never across an await.
    bindings: Mutex<BindingRegistry>,
    gauge: Arc<MemoryGauge>,
    persistence: Option<Arc<Persistence>>,
    counters: Arc<BrokerCounters>,
    /// Direct reply-to consumers by their reply name.
    reply_targets: RwLock<HashMap<ShortStr, ReplyTarget>>,
    /// Exclusive queues by owning connection, so that closing one costs
    /// what it owns, not what the vhost holds.
    exclusive_queues: Mutex<HashMap<u64, HashMap<ShortStr, Arc<Queue>>>>,
    /// Its policies (`policies`), replaced whole on each change.
    policies: RwLock<Arc<VhostPolicies>>,
    /// Set when the vhost is deleted: declares are refused from then on
    /// (checked under the registries' write locks, so nothing declared
    /// after it is missed by [`Vhost::delete_everything_step`]).
    deleted: AtomicBool,
}

/// A channel's last default-exchange lookup, for [`Vhost::queue_remembered`].
#[derive(Debug)]
pub struct RememberedQueue {
    /// The vhost's `queue_changes` when it was looked up.
    changes: u64,
    queue: Arc<Queue>,
}

/// Whether a binding operation adds the binding or removes it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BindingChange {
    /// queue.bind, exchange.bind.
    Bind,
    /// queue.unbind, exchange.unbind.
    Unbind,
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
    /// Refuse to create the queue when the vhost has this many already
    /// (RabbitMQ's vhost limit `max-queues`).
    pub max_queues: Option<usize>,
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

fn lock<T>(mutex: &Mutex<T>) -> MutexGuard<'_, T> {
    mutex.lock().unwrap_or_else(|e| e.into_inner())
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
            queue_changes: AtomicU64::new(0),
            bindings: Mutex::new(BindingRegistry::default()),
            gauge,
            persistence,
            counters,
            reply_targets: RwLock::new(HashMap::new()),
            exclusive_queues: Mutex::new(HashMap::new()),
            policies: RwLock::default(),
            deleted: AtomicBool::new(false),
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

    /// [`Vhost::queue`] through a channel's memory of its last lookup:
    /// while no queue was added or removed since, the same name finds the
    /// same queue without the registry's lock or a hash. A publish to the
    /// default exchange looks its queue up once per message (the lock and
    /// the SipHash showed in a no-ack publish's profile).
    pub fn queue_remembered(
        &self,
        name: &ShortStr,
        last: &mut Option<RememberedQueue>,
    ) -> Option<Arc<Queue>> {
        // Read before the lookup: a change after this load makes the
        // memory stale at once, even one the lookup already saw.
        let changes = self.queue_changes.load(Ordering::Acquire);
        if let Some(last) = last {
            if last.changes == changes && last.queue.name == *name {
                return Some(Arc::clone(&last.queue));
            }
        }
        let queue = self.queue(name)?;
        *last = Some(RememberedQueue {
            changes,
            queue: Arc::clone(&queue),
        });
        Some(queue)
    }

    /// How many queues the vhost has.
    #[cfg(feature = "mqtt")]
    pub fn queue_count(&self) -> usize {
        read(&self.queues).len()
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
        self.queue(name)
            .ok_or_else(|| AmqpError::no_queue(name, &self.name))
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
        let resource = format!("exchange '{}' in vhost '{}'", decl.name, self.name);
        if let Some(alternate) = decl.options.arguments.get("alternate-exchange") {
            if !matches!(alternate, leveret_protocol::FieldValue::LongStr(_)) {
                return Err(AmqpError::precondition_failed(format_args!(
                    "invalid type '{}' for arg 'alternate-exchange' in {resource}",
                    arguments::type_name(alternate)
                )));
            }
        }
        if kind == ExchangeKind::ConsistentHash {
            let refused = decl.options.arguments.iter().find_map(|(key, _)| {
                arguments::known(arguments::Scope::Exchange, key.as_bytes())
                    .and_then(|argument| arguments::refusal(argument, &resource))
            });
            if let Some(refused) = refused {
                return Err(refused);
            }
        }
        let mut exchanges = write(&self.exchanges);
        self.refuse_if_deleted()?;
        if let Some(existing) = exchanges.get(&decl.name) {
            let field =
                |key: &str, received: &dyn std::fmt::Display, current: &dyn std::fmt::Display| {
                    arguments::inequivalent(
                        key,
                        &resource,
                        &format!("'{received}'"),
                        &format!("'{current}'"),
                    )
                };
            let (o, d) = (&existing.options, &decl.options);
            if existing.kind != kind {
                return Err(field("type", &kind.name(), &existing.kind.name()));
            }
            for (key, current, received) in [
                ("durable", o.durable, d.durable),
                ("auto_delete", o.auto_delete, d.auto_delete),
                ("internal", o.internal, d.internal),
            ] {
                if current != received {
                    return Err(field(key, &received, &current));
                }
            }
            if let Some(error) = arguments::first_inequivalent(
                arguments::Scope::Exchange,
                &o.arguments,
                &d.arguments,
                &resource,
            ) {
                return Err(error);
            }
            return Ok(Arc::clone(existing));
        }
        let exchange = Arc::new(Exchange::new(decl.name.clone(), kind, decl.options));
        exchanges.insert(decl.name, Arc::clone(&exchange));
        drop(exchanges);
        self.apply_exchange_policies(&exchange);
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
    pub fn delete_exchange(self: &Arc<Self>, name: &ShortStr, if_unused: bool) -> AmqpResult<()> {
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
        // Only the exchange looked up above: one declared again under the
        // name meanwhile is another, and stays (a publisher's channel may
        // already hold it, trusting that a removed exchange is marked).
        let removed = {
            let mut exchanges = write(&self.exchanges);
            let current = exchanges
                .get(name)
                .is_some_and(|e| Arc::ptr_eq(e, &exchange));
            current && exchanges.remove(name).is_some()
        };
        if removed {
            self.forget_exchange(&exchange);
        }
        Ok(())
    }

    fn is_bound_destination(&self, exchange: &Arc<Exchange>) -> bool {
        lock(&self.bindings).is_destination(&Destination::Exchange(Arc::clone(exchange)))
    }

    /// queue.declare; returns the queue and whether it was created.
    pub fn declare_queue(
        &self,
        decl: QueueDeclaration,
        connection_id: u64,
    ) -> AmqpResult<(Arc<Queue>, bool)> {
        if let Some(existing) = self.queue(&decl.name) {
            check_exclusive(&existing, connection_id, &self.name)?;
            if !decl.passive {
                let (o, d) = (&existing.options, &decl.options);
                if o.exclusive_owner.is_some() != d.exclusive_owner.is_some() {
                    return Err(exclusive_locked(&existing.name, &self.name));
                }
                let resource = format!("queue '{}' in vhost '{}'", decl.name, self.name);
                for (key, current, received) in [
                    ("durable", o.durable, d.durable),
                    ("auto_delete", o.auto_delete, d.auto_delete),
                ] {
                    if current != received {
                        return Err(arguments::inequivalent(
                            key,
                            &resource,
                            &format!("'{received}'"),
                            &format!("'{current}'"),
                        ));
                    }
                }
                let current = existing.arguments();
                let differing = if existing.is_stream() {
                    arguments::first_inequivalent_on_stream(&o.arguments, &d.arguments, &resource)
                } else if arguments::marks_an_mqtt_queue(&current) {
                    // MQTT keeps a group queue's x-expires at its members',
                    // a session queue's at its session's (a redeclaration's,
                    // an old export's, is stale).
                    let (mut current, mut requested) = (current, d.arguments.clone());
                    current.remove("x-expires");
                    requested.remove("x-expires");
                    let scope = arguments::Scope::Queue;
                    arguments::first_inequivalent(scope, &current, &requested, &resource)
                } else {
                    let scope = arguments::Scope::Queue;
                    arguments::first_inequivalent(scope, &current, &d.arguments, &resource)
                };
                if let Some(error) = differing {
                    return Err(error);
                }
            }
            existing.touch();
            return Ok((existing, false));
        }
        if decl.passive {
            return Err(AmqpError::no_queue(&decl.name, &self.name));
        }
        self.create_queue(decl, connection_id)
    }

    /// Creates the queue `decl` names, not found by a lookup just before;
    /// one declared meanwhile (by another channel, or an MQTT member) is
    /// returned as it is, not compared with `decl`, unless another
    /// connection owns it (405).
    fn create_queue(
        &self,
        decl: QueueDeclaration,
        connection_id: u64,
    ) -> AmqpResult<(Arc<Queue>, bool)> {
        if !decl.server_named && decl.name.as_bytes().starts_with(b"amq.") {
            return Err(AmqpError::access_refused(format_args!(
                "queue name '{}' contains reserved prefix 'amq.*'",
                decl.name
            )));
        }
        if crate::queue::is_stream(&decl.options.arguments) {
            return self.declare_stream(decl);
        }
        let args = QueueArgs::parse(&decl.options.arguments, &decl.name, &self.name)?;
        let (policies, applied) = self.policies_for(ObjectKind::Queue, decl.name.as_bytes());
        let mut queues = write(&self.queues);
        self.refuse_if_deleted()?;
        if let Some(existing) = queues.get(&decl.name) {
            // Declared by another channel between our check and the lock.
            check_exclusive(existing, connection_id, &self.name)?;
            return Ok((Arc::clone(existing), false));
        }
        if let Some(max) = decl.max_queues.filter(|max| queues.len() >= *max) {
            return Err(AmqpError::precondition_failed(format_args!(
                "cannot declare queue '{}': queue limit in vhost '{}' ({max}) is reached",
                decl.name, self.name
            )));
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
            self.name.clone(),
            decl.options,
            args,
            Arc::clone(&self.gauge),
            durable_store,
            Arc::clone(&self.counters),
        ));
        self.give_new_queue(&queue, applied);
        if let Some(owner) = queue.options.exclusive_owner {
            lock(&self.exclusive_queues)
                .entry(owner)
                .or_default()
                .insert(decl.name.clone(), Arc::clone(&queue));
        }
        queues.insert(decl.name, Arc::clone(&queue));
        self.queue_changes.fetch_add(1, Ordering::Release);
        drop(queues);
        self.catch_up_queue(&queue, &policies);
        Ok((queue, true))
    }

    /// queue.declare of a stream (`x-queue-type: stream`), not declared
    /// before: RabbitMQ's rules checked, its log opened in the data
    /// directory, its definition stored.
    fn declare_stream(&self, decl: QueueDeclaration) -> AmqpResult<(Arc<Queue>, bool)> {
        let options = &decl.options;
        let args = StreamArgs::parse(
            &options.arguments,
            options.durable,
            options.exclusive_owner.is_some(),
            options.auto_delete,
            decl.server_named,
            &decl.name,
            &self.name,
        )?;
        let (policies, applied) = self.policies_for(ObjectKind::Stream, decl.name.as_bytes());
        let args = args
            .with_policy_segment_size(&options.arguments, applied.stream_max_segment_size_bytes());
        let Some(persistence) = self.persistence.as_ref().map(Arc::clone) else {
            return Err(AmqpError::precondition_failed(format_args!(
                "cannot declare stream '{}' in vhost '{}': this broker keeps nothing on disk (streams need a data directory)",
                decl.name, self.name
            )));
        };
        let mut queues = write(&self.queues);
        if let Some(existing) = queues.get(&decl.name) {
            return Ok((Arc::clone(existing), false));
        }
        if let Some(max) = decl.max_queues.filter(|max| queues.len() >= *max) {
            return Err(AmqpError::precondition_failed(format_args!(
                "cannot declare queue '{}': queue limit in vhost '{}' ({max}) is reached",
                decl.name, self.name
            )));
        }
        let id = persistence.next_queue_id();
        let stream = match Stream::open(args, Arc::clone(&persistence), id, true) {
            Some(Ok(stream)) => stream,
            Some(Err(e)) => {
                tracing::error!(queue = %decl.name, vhost = %self.name, error = %e, "cannot create a stream's files");
                return Err(AmqpError::internal_error(format_args!(
                    "cannot create the files of stream '{}': {e}",
                    decl.name
                )));
            }
            None => {
                return Err(AmqpError::precondition_failed(format_args!(
                    "cannot declare stream '{}' in vhost '{}': this broker keeps nothing on disk (streams need a data directory)",
                    decl.name, self.name
                )))
            }
        };
        persistence.submit(vec![StoreOp::PutQueue(QueueRecord {
            vhost: self.name.clone(),
            name: decl.name.clone(),
            id,
            auto_delete: false,
            arguments: decl.options.arguments.clone(),
        })]);
        let queue = Arc::new(Queue::new_stream(
            decl.name.clone(),
            self.name.clone(),
            decl.options,
            stream,
            Arc::clone(&self.gauge),
            (persistence, id),
            Arc::clone(&self.counters),
        ));
        self.give_new_queue(&queue, applied);
        queues.insert(decl.name, Arc::clone(&queue));
        self.queue_changes.fetch_add(1, Ordering::Release);
        drop(queues);
        self.catch_up_queue(&queue, &policies);
        Ok((queue, true))
    }

    /// Marks the vhost deleted: from now on nothing can be declared in it.
    pub fn mark_deleted(&self) {
        // Under both write locks, so that a declare holding either has
        // either inserted already (and is found by the deletion's sweep)
        // or sees the mark.
        let _queues = write(&self.queues);
        let _exchanges = write(&self.exchanges);
        self.deleted.store(true, Ordering::SeqCst);
        // With the fence in `is_deleted`: a connection that registers
        // itself and then checks the mark either sees it or is seen by the
        // deletion's look at the registry that follows.
        std::sync::atomic::fence(Ordering::SeqCst);
    }

    /// Whether the vhost has been deleted.
    pub fn is_deleted(&self) -> bool {
        std::sync::atomic::fence(Ordering::SeqCst);
        self.deleted.load(Ordering::SeqCst)
    }

    fn refuse_if_deleted(&self) -> AmqpResult<()> {
        if self.is_deleted() {
            return Err(AmqpError::not_found(format_args!(
                "vhost '{}' is deleted",
                self.name
            )));
        }
        Ok(())
    }

    /// One slice of deleting everything in a vhost marked deleted: its
    /// queues (with their messages and bindings, on disk too; consumers
    /// are told with basic.cancel), then every exchange, the predefined
    /// ones included, with their bindings. Each queue or exchange is one
    /// step of `slice`; [`Progress::Done`] once the vhost holds nothing.
    pub fn delete_everything_step(self: &Arc<Self>, slice: &mut Slice) -> Progress {
        debug_assert!(self.is_deleted(), "only a deleted vhost is emptied");
        // Chunks, not one lookup per queue: finding the first of a map
        // emptied from the front costs a scan of its empty buckets.
        loop {
            let queues: Vec<Arc<Queue>> = read(&self.queues)
                .values()
                .take(UNBIND_STEP)
                .cloned()
                .collect();
            if queues.is_empty() {
                break;
            }
            for queue in queues {
                self.delete_queue(&queue).notify();
                if slice.step() {
                    return Progress::More;
                }
            }
        }
        loop {
            let exchanges: Vec<Arc<Exchange>> = {
                let mut exchanges = write(&self.exchanges);
                let names: Vec<ShortStr> = exchanges.keys().take(UNBIND_STEP).cloned().collect();
                names
                    .iter()
                    .filter_map(|name| exchanges.remove(name))
                    .collect()
            };
            if exchanges.is_empty() {
                return Progress::Done;
            }
            for exchange in exchanges {
                // Removed from the registry above: forgotten even when the
                // slice is spent.
                self.forget_exchange(&exchange);
                slice.step();
            }
            if slice.is_spent() {
                return Progress::More;
            }
        }
    }

    /// Deletes a queue: its bindings and messages go with it; its consumers
    /// come back in [`Deleted`], to be notified.
    pub fn delete_queue(self: &Arc<Self>, queue: &Arc<Queue>) -> Deleted {
        {
            let mut queues = write(&self.queues);
            match queues.get(queue.name.as_bytes()) {
                Some(current) if Arc::ptr_eq(current, queue) => {
                    queues.remove(queue.name.as_bytes());
                    self.queue_changes.fetch_add(1, Ordering::Release);
                }
                _ => return Deleted::default(),
            }
        }
        if let Some(owner) = queue.options.exclusive_owner {
            let mut exclusive = lock(&self.exclusive_queues);
            if let Some(owned) = exclusive.get_mut(&owner) {
                owned.remove(queue.name.as_bytes());
                if owned.is_empty() {
                    exclusive.remove(&owner);
                }
            }
        }
        let destination = Destination::Queue(Arc::clone(queue));
        if queue.store_id().is_some() {
            // Under the registry lock, so that these deletes reach the store
            // before a binding of a queue of the same name declared next.
            let registry = lock(&self.bindings);
            let mut ops = Vec::new();
            registry.for_each_binding_to(&destination, |source, binding| {
                ops.extend(
                    self.binding_record(source, binding)
                        .map(StoreOp::DeleteBinding),
                );
            });
            ops.push(StoreOp::DeleteQueue {
                vhost: self.name.clone(),
                name: queue.name.clone(),
            });
            self.persist(ops);
        }
        self.unbind_in_steps(destination);
        queue.delete()
    }

    /// queue.declare of an MQTT shared subscription group's queue: one
    /// that exists is joined as it is, without comparing its flags and
    /// arguments with `decl`'s (members of a group may differ in
    /// durability and expiry: MQTT 5.0 4.8.2), unless another connection
    /// owns it; one that does not is created as `decl` says. Either way
    /// the member holds it ([`Queue::join`]) until the [`QueueJoin`] is
    /// dropped (once its consume has arrived, or the member has gone), so
    /// neither x-expires nor auto-delete can take it from under the
    /// member's bind and consume. One that is going (auto-delete, expiry)
    /// is not joined: the caller finishes its deletion, outside any lock
    /// of its own, and tries again.
    #[cfg(feature = "mqtt")]
    pub fn join_or_declare_queue(
        self: &Arc<Self>,
        decl: QueueDeclaration,
    ) -> AmqpResult<JoinAttempt> {
        let (queue, created) = match self.queue(&decl.name) {
            Some(existing) if existing.options.exclusive_owner.is_some() => {
                return Err(exclusive_locked(&existing.name, &self.name));
            }
            Some(existing) => (existing, false),
            // Not exclusive: no connection owns it. One declared since
            // the lookup (an AMQP client's, say) is joined as it is too,
            // never compared with `decl` (no 406 inequivalent arg).
            None => self.create_queue(decl, 0)?,
        };
        if queue.join(created) {
            let vhost = Arc::clone(self);
            return Ok(JoinAttempt::Joined(QueueJoin { vhost, queue }, created));
        }
        Ok(JoinAttempt::Going(queue))
    }

    /// Gives `queue`, if it is still this vhost's, its own expiry (and
    /// `mark`, if any: [`Queue::set_expires`]); false if it is gone. Under
    /// the queues' lock, so that its record reaches the store before a
    /// deletion's.
    #[cfg(feature = "mqtt")]
    pub fn set_queue_expires(
        &self,
        queue: &Arc<Queue>,
        expires: Option<u64>,
        mark: Option<&'static str>,
    ) -> bool {
        let queues = read(&self.queues);
        match queues.get(queue.name.as_bytes()) {
            Some(current) if Arc::ptr_eq(current, queue) => queue.set_expires(expires, mark),
            _ => false,
        }
    }

    /// The binding keys and arguments of `queue`'s bindings from the
    /// exchange `source` (an MQTT session resumed from its queue's
    /// bindings, its subscription options in their arguments), at most
    /// `limit` of them.
    #[cfg(feature = "mqtt")]
    pub fn bindings_to(
        &self,
        source: &ShortStr,
        queue: &Arc<Queue>,
        limit: usize,
    ) -> Vec<(ShortStr, FieldTable)> {
        let mut found = Vec::new();
        let destination = Destination::Queue(Arc::clone(queue));
        lock(&self.bindings).for_each_binding_to(&destination, |exchange, binding| {
            if found.len() < limit && exchange.name == *source {
                found.push((binding.routing_key.clone(), binding.arguments.clone()));
            }
        });
        found
    }

    /// Deletes an auto-delete exchange that has lost its last binding.
    fn auto_delete_exchange(self: &Arc<Self>, exchange: &Arc<Exchange>) {
        if !exchange.options.auto_delete {
            return;
        }
        let removed = {
            // No binding can be added between the check and the removal.
            let _registry = lock(&self.bindings);
            !exchange.has_bindings() && {
                let mut exchanges = write(&self.exchanges);
                let current = exchanges
                    .get(exchange.name.as_bytes())
                    .is_some_and(|e| Arc::ptr_eq(e, exchange));
                current && exchanges.remove(exchange.name.as_bytes()).is_some()
            }
        };
        if removed {
            self.forget_exchange(exchange);
        }
    }

    /// Removes a deleted exchange's bindings, in memory and on disk.
    fn forget_exchange(self: &Arc<Self>, exchange: &Arc<Exchange>) {
        exchange.mark_deleted();
        let destination = Destination::Exchange(Arc::clone(exchange));
        if exchange.options.durable {
            // Under the registry lock, as in `delete_queue`.
            let registry = lock(&self.bindings);
            let mut ops = Vec::new();
            exchange.for_each_binding(|binding| {
                ops.extend(
                    self.binding_record(exchange, binding)
                        .map(StoreOp::DeleteBinding),
                );
            });
            registry.for_each_binding_to(&destination, |source, binding| {
                ops.extend(
                    self.binding_record(source, binding)
                        .map(StoreOp::DeleteBinding),
                );
            });
            ops.push(StoreOp::DeleteExchange {
                vhost: self.name.clone(),
                name: exchange.name.clone(),
            });
            self.persist(ops);
        }
        self.unbind_in_steps(destination);
    }

    /// Removes every binding to a deleted queue or exchange (and from a
    /// deleted exchange): the first [`UNBIND_STEP`] now, the rest in a task
    /// that yields between steps, so that no deletion holds the thread for
    /// long whatever its number of bindings. Meanwhile a deleted exchange
    /// routes nothing, and a deleted queue drops what still reaches it (as
    /// what was routed just before its deletion). The store was told at
    /// deletion. Exchanges left without bindings are auto-deleted.
    fn unbind_in_steps(self: &Arc<Self>, doomed: Destination) {
        let vhost = Arc::clone(self);
        crate::slice::finish_in_background(move |_| match vhost.unbind_step(&doomed) {
            true => Progress::Done,
            false => Progress::More,
        });
    }

    /// One step of [`Self::unbind_in_steps`]; true once nothing is left.
    fn unbind_step(self: &Arc<Self>, doomed: &Destination) -> bool {
        let mut budget = UNBIND_STEP;
        let mut touched = Vec::new();
        let done = {
            let mut registry = lock(&self.bindings);
            let to_done = registry.unbind_destination(doomed, &mut budget, &mut touched);
            let from_done = match doomed {
                Destination::Exchange(exchange) => registry.unbind_source(exchange, &mut budget),
                Destination::Queue(_) => true,
            };
            to_done && from_done
        };
        touched.dedup_by(|a, b| Arc::ptr_eq(a, b));
        for exchange in touched {
            self.auto_delete_exchange(&exchange);
        }
        done
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

    /// Adds a binding in memory and, between durable ends, on disk; 404
    /// if an end was deleted since the caller looked it up.
    fn add_binding(&self, source: &Arc<Exchange>, binding: Binding) -> AmqpResult<()> {
        // Store ops go out under the registry lock, in the order of the
        // changes they record.
        let mut registry = lock(&self.bindings);
        self.check_current(source, &binding.destination)?;
        let record = self.binding_record(source, &binding);
        if registry.bind(source, binding) {
            if let Some(record) = record {
                self.persist(vec![StoreOp::PutBinding(record)]);
            }
        }
        Ok(())
    }

    /// 404 unless both ends of a binding are still declared (not deleted,
    /// nor replaced by a namesake).
    fn check_current(&self, source: &Arc<Exchange>, destination: &Destination) -> AmqpResult<()> {
        self.check_current_exchange(source)?;
        match destination {
            Destination::Exchange(exchange) => self.check_current_exchange(exchange),
            Destination::Queue(queue) => {
                let current = read(&self.queues)
                    .get(queue.name.as_bytes())
                    .is_some_and(|q| Arc::ptr_eq(q, queue));
                if current {
                    Ok(())
                } else {
                    Err(AmqpError::no_queue(&queue.name, &self.name))
                }
            }
        }
    }

    fn check_current_exchange(&self, exchange: &Arc<Exchange>) -> AmqpResult<()> {
        let current = read(&self.exchanges)
            .get(exchange.name.as_bytes())
            .is_some_and(|e| Arc::ptr_eq(e, exchange));
        if current {
            Ok(())
        } else {
            Err(AmqpError::not_found(format_args!(
                "no exchange '{}' in vhost '{}'",
                exchange.name, self.name
            )))
        }
    }

    /// Removes a binding; true if it existed.
    fn remove_binding(&self, source: &Arc<Exchange>, binding: &Binding) -> bool {
        let mut registry = lock(&self.bindings);
        let removed = registry.unbind(source, binding);
        if removed {
            if let Some(record) = self.binding_record(source, binding) {
                self.persist(vec![StoreOp::DeleteBinding(record)]);
            }
        }
        removed
    }

    /// queue.bind and queue.unbind (unbinding what was never bound
    /// succeeds, as in RabbitMQ).
    pub fn bind_queue(
        self: &Arc<Self>,
        queue: &Arc<Queue>,
        exchange: &ShortStr,
        routing_key: ShortStr,
        arguments: FieldTable,
        change: BindingChange,
    ) -> AmqpResult<()> {
        let source = self.bindable_source(exchange)?;
        let binding = Binding {
            destination: Destination::Queue(Arc::clone(queue)),
            routing_key,
            arguments,
        };
        if change == BindingChange::Bind {
            check_binding(&source, &binding)?;
            self.add_binding(&source, binding)?;
        } else if self.remove_binding(&source, &binding) {
            self.auto_delete_exchange(&source);
        }
        Ok(())
    }

    /// exchange.bind and exchange.unbind.
    pub fn bind_exchange(
        self: &Arc<Self>,
        destination: &ShortStr,
        source: &ShortStr,
        routing_key: ShortStr,
        arguments: FieldTable,
        change: BindingChange,
    ) -> AmqpResult<()> {
        let missing_end = self.exchange(destination).is_none() || self.exchange(source).is_none();
        if change == BindingChange::Unbind && missing_end {
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
        if change == BindingChange::Bind {
            check_binding(&from, &binding)?;
            self.add_binding(&from, binding)?;
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

    /// The broker-wide counters this vhost's queues add into.
    pub(crate) fn counters(&self) -> &BrokerCounters {
        &self.counters
    }

    /// Routes dead letters a queue operation returned, iteratively and
    /// with RabbitMQ's cycle rule (see [`deadletter`]).
    pub fn dead_letter(self: &Arc<Self>, letters: DeadLetters) {
        deadletter::route(self, letters);
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

    /// Re-creates a stored queue at start (its messages are restored by
    /// the caller); a stream whose files are damaged is the error (see
    /// [`Vhost::restore_stream`]).
    pub fn restore_queue(&self, record: &QueueRecord) -> Result<Option<Arc<Queue>>, String> {
        if crate::queue::is_stream(&record.arguments) {
            return self.restore_stream(record);
        }
        // Stored before these arguments were refused (a quorum queue taken
        // as a classic one): it stays the classic queue it was.
        let (arguments, dropped) = arguments::classic_queue_arguments(&record.arguments);
        if !dropped.is_empty() {
            tracing::warn!(queue = %record.name, vhost = %self.name, ?dropped, "stored queue has arguments a classic queue refuses; restored without them");
        }
        let options = QueueOptions {
            durable: true,
            exclusive_owner: None,
            auto_delete: record.auto_delete,
            arguments,
        };
        let args = match QueueArgs::parse(&options.arguments, &record.name, &self.name) {
            Ok(args) => args,
            Err(e) => {
                tracing::warn!(queue = %record.name, error = %e, "stored queue arguments no longer valid; using none");
                QueueArgs::default()
            }
        };
        let Some(persistence) = self.persistence.as_ref().map(Arc::clone) else {
            return Ok(None);
        };
        let queue = Arc::new(Queue::new(
            record.name.clone(),
            self.name.clone(),
            options,
            args,
            Arc::clone(&self.gauge),
            Some((persistence, record.id)),
            Arc::clone(&self.counters),
        ));
        write(&self.queues).insert(record.name.clone(), Arc::clone(&queue));
        self.queue_changes.fetch_add(1, Ordering::Release);
        Ok(Some(queue))
    }

    /// Re-creates a stored stream at start, opening (and checking) its
    /// log: damage found is the error (what is wrong, naming the file)
    /// unless the broker recovers (`--recover`).
    fn restore_stream(&self, record: &QueueRecord) -> Result<Option<Arc<Queue>>, String> {
        let Some(persistence) = self.persistence.as_ref().map(Arc::clone) else {
            return Ok(None);
        };
        let args = match StreamArgs::parse(
            &record.arguments,
            true,
            false,
            false,
            false,
            &record.name,
            &self.name,
        ) {
            Ok(args) => args,
            Err(e) => {
                tracing::error!(queue = %record.name, vhost = %self.name, error = %e, "stored stream's arguments no longer valid; not restored (its files are kept)");
                return Ok(None);
            }
        };
        let stream = match Stream::open(args, Arc::clone(&persistence), record.id, false) {
            None => return Ok(None),
            Some(Ok(stream)) => stream,
            Some(Err(e)) if e.kind() == std::io::ErrorKind::InvalidData => {
                return Err(format!(
                    "stream '{}' in vhost '{}': {e}",
                    record.name, self.name
                ));
            }
            Some(Err(e)) => {
                tracing::error!(queue = %record.name, vhost = %self.name, error = %e, "cannot open a stream's files; not restored");
                return Ok(None);
            }
        };
        let options = QueueOptions {
            durable: true,
            exclusive_owner: None,
            auto_delete: false,
            arguments: record.arguments.clone(),
        };
        let queue = Arc::new(Queue::new_stream(
            record.name.clone(),
            self.name.clone(),
            options,
            stream,
            Arc::clone(&self.gauge),
            (persistence, record.id),
            Arc::clone(&self.counters),
        ));
        write(&self.queues).insert(record.name.clone(), Arc::clone(&queue));
        self.queue_changes.fetch_add(1, Ordering::Release);
        Ok(Some(queue))
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
        lock(&self.bindings).bind(
            &source,
            Binding {
                destination,
                routing_key: record.routing_key.clone(),
                arguments: record.arguments.clone(),
            },
        );
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

    /// Deletes the exclusive queues of a closed connection, a slice at a
    /// time, the first slice now.
    pub fn drop_exclusive(self: &Arc<Self>, connection_id: u64) {
        let Some(owned) = lock(&self.exclusive_queues).remove(&connection_id) else {
            return;
        };
        let mut owned = owned.into_values();
        let vhost = Arc::clone(self);
        crate::slice::finish_in_background(move |slice| {
            for queue in owned.by_ref() {
                vhost.delete_queue(&queue).notify();
                if slice.step() {
                    return Progress::More;
                }
            }
            Progress::Done
        });
    }

    /// Expires `queue`'s head messages past their TTL and routes their
    /// dead letters, a slice at a time, yielding between slices.
    pub async fn expire(self: &Arc<Self>, queue: &Queue) {
        let now = Instant::now();
        let mut slice = Slice::start();
        while self.expire_step(queue, now, &mut slice) == Progress::More {
            tokio::task::yield_now().await;
            slice = Slice::start();
        }
    }

    /// Expires messages and routes their dead letters until `slice` is
    /// spent or nothing expired is left.
    fn expire_step(self: &Arc<Self>, queue: &Queue, now: Instant, slice: &mut Slice) -> Progress {
        loop {
            let (dead, progress) = queue.expire_at(now, slice);
            self.dead_letter(dead);
            if progress == Progress::Done {
                return Progress::Done;
            }
            if slice.is_spent() {
                return Progress::More;
            }
        }
    }

    /// Periodic housekeeping: expires messages past their TTL (dispatching
    /// what a consumer waiting behind them can now take), gives back the
    /// room of idle queues and deletes queues past x-expires, yielding
    /// whenever a slice is spent.
    pub async fn sweep(self: &Arc<Self>) {
        let now = Instant::now();
        let mut slice = Slice::start();
        for queue in self.queues() {
            while self.sweep_queue(&queue, now, &mut slice) == Progress::More {
                tokio::task::yield_now().await;
                slice = Slice::start();
            }
            yield_if_spent(&mut slice).await;
        }
    }

    /// [`Vhost::sweep`] as of `now`, all at once (for tests of the core).
    #[cfg(test)]
    pub fn sweep_at(self: &Arc<Self>, now: Instant) {
        for queue in self.queues() {
            while self.sweep_queue(&queue, now, &mut Slice::start()) == Progress::More {}
        }
    }

    /// One queue's part of a sweep, within `slice`.
    fn sweep_queue(
        self: &Arc<Self>,
        queue: &Arc<Queue>,
        now: Instant,
        slice: &mut Slice,
    ) -> Progress {
        if self.expire_step(queue, now, slice) == Progress::More {
            return Progress::More;
        }
        self.dead_letter(queue.dispatch());
        queue.release_idle_room();
        if queue.take_expired(now) {
            tracing::debug!(queue = %queue.name, "queue expired (x-expires)");
            self.delete_queue(queue).notify();
        }
        slice.step();
        Progress::Done
    }
}

/// Exchange-to-exchange bindings may form a cycle (`a` bound to `b`, `b`
/// to `a`) in which each exchange holds the other: a vhost that goes away
/// (its broker stopped) breaks them, so an embedder that starts and stops
/// brokers in one process leaks nothing.
impl Drop for Vhost {
    fn drop(&mut self) {
        let exchanges = self.exchanges.get_mut().unwrap_or_else(|e| e.into_inner());
        for exchange in exchanges.values() {
            exchange.forget_routes();
        }
    }
}

fn default_exchange_refusal(name: &ShortStr, vhost: &ShortStr) -> AmqpError {
    AmqpError::access_refused(format_args!(
        "operation not permitted on the default exchange '{}' in vhost '{}'",
        name, vhost
    ))
}

/// What a binding's kind of exchange asks of its key and arguments: a
/// valid `x-match` (headers), a weight (x-consistent-hash).
fn check_binding(exchange: &Exchange, binding: &Binding) -> AmqpResult<()> {
    match exchange.kind {
        ExchangeKind::Headers if !crate::exchange::valid_x_match(&binding.arguments) => {
            Err(AmqpError::precondition_failed(
                "invalid x-match field value; expected all, any, all-with-x, or any-with-x",
            ))
        }
        ExchangeKind::ConsistentHash
            if consistent_hash::weight(&binding.routing_key).is_none() =>
        {
            Err(AmqpError::precondition_failed(format_args!(
                "the binding key of an x-consistent-hash exchange is a weight, an integer from 1 to {}; got '{}'",
                consistent_hash::MAX_WEIGHT,
                binding.routing_key
            )))
        }
        _ => Ok(()),
    }
}

/// Exclusive queues belong to one connection: 405 for any other.
pub fn check_exclusive(queue: &Queue, connection_id: u64, vhost: &ShortStr) -> AmqpResult<()> {
    match queue.options.exclusive_owner {
        Some(owner) if owner != connection_id => Err(exclusive_locked(&queue.name, vhost)),
        _ => Ok(()),
    }
}

/// What [`Vhost::join_or_declare_queue`] did.
#[cfg(feature = "mqtt")]
#[derive(Debug)]
pub enum JoinAttempt {
    /// Joined: the hold, and whether the queue was created for it.
    Joined(QueueJoin, bool),
    /// The queue of that name is going (auto-delete, expiry): its
    /// deletion is the caller's to finish ([`Vhost::delete_queue`]; whoever
    /// comes second finds it gone) before it tries again.
    Going(Arc<Queue>),
}

/// An MQTT shared subscription's member's hold on its group's queue,
/// from [`Vhost::join_or_declare_queue`] until dropped (the member's
/// consume has arrived, or the member has gone): then the queue is
/// auto-deleted if its last consumer left meanwhile, or if none ever came
/// to a queue created for the join.
#[cfg(feature = "mqtt")]
#[derive(Debug)]
pub struct QueueJoin {
    vhost: Arc<Vhost>,
    queue: Arc<Queue>,
}

#[cfg(all(feature = "mqtt", test))]
impl QueueJoin {
    /// The queue joined.
    pub fn queue(&self) -> &Arc<Queue> {
        &self.queue
    }
}

#[cfg(feature = "mqtt")]
impl Drop for QueueJoin {
    fn drop(&mut self) {
        if self.queue.leave_join() {
            tracing::debug!(queue = %self.queue.name, "MQTT shared subscription group's queue auto-deleted (its joining member's hold released)");
            self.vhost.delete_queue(&self.queue).notify();
        }
    }
}

/// RabbitMQ's 405 for a queue another connection owns, and for a redeclare
/// whose `exclusive` flag differs from the queue's (either way round).
fn exclusive_locked(queue: &ShortStr, vhost: &ShortStr) -> AmqpError {
    AmqpError::resource_locked(format_args!(
        "cannot obtain exclusive access to locked queue '{queue}' in vhost '{vhost}'. It could be originally declared on another connection or the exclusive property value does not match that of the original declaration."
    ))
}

mod deadletter;
mod policies;
pub mod publish;
mod routing;

/// RabbitMQ compares the arguments it validates; the first that differs.
#[cfg(test)]
mod tests;
