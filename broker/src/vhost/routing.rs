//! Routing a published message: from the exchange it was published to,
//! through exchange-to-exchange bindings and alternate exchanges, to the
//! set of queues it reaches, each once. The hot path of every publish; it
//! uses the vhost's lookups and the exchanges' own routing, and takes no
//! lock longer than one exchange's lookup. Each exchange is walked at most
//! once per message (so cycles of bindings end), and every set it keeps is
//! hashed, so a message costs what the bindings it meets cost.

use crate::exchange::{Destination, DestinationId, Exchange};
use crate::queue::Queue;
use crate::vhost::{RememberedQueue, Vhost};
use leveret_protocol::{FieldTable, ShortStr};
use std::collections::HashSet;
use std::sync::Arc;

impl Vhost {
    /// Collects in `queues` every queue a message published to `exchange`
    /// reaches, following exchange-to-exchange bindings and alternate
    /// exchanges, each queue once. `queues` is a buffer the caller reuses;
    /// `last` remembers the default exchange's last lookup
    /// ([`Vhost::queue_remembered`]).
    pub fn route(
        &self,
        exchange: &Arc<Exchange>,
        routing_key: &ShortStr,
        headers: Option<&FieldTable>,
        queues: &mut Vec<Arc<Queue>>,
        last: &mut Option<RememberedQueue>,
    ) {
        queues.clear();
        if exchange.name.is_empty() {
            queues.extend(self.queue_remembered(routing_key, last));
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
            let mut visited: HashSet<DestinationId> = HashSet::new();
            visited.insert(DestinationId::of(exchange));
            while let Some(following) = next.pop() {
                if !visited.insert(DestinationId::of(&following)) {
                    continue;
                }
                following.route(routing_key, headers, |destination| match destination {
                    Destination::Queue(q) => queues.push(Arc::clone(q)),
                    Destination::Exchange(e) => next.push(Arc::clone(e)),
                });
            }
        }
        if queues.is_empty() {
            // Alternate exchanges, followed until one routes or a cycle.
            let mut alternate = exchange.alternate();
            let mut tried: HashSet<ShortStr> = HashSet::from([exchange.name.clone()]);
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
                    tried.insert(name);
                }
            }
        }
        if queues.len() > 1 {
            queues.sort_by_key(|q| Arc::as_ptr(q) as usize);
            queues.dedup_by(|a, b| Arc::ptr_eq(a, b));
        }
    }
}
