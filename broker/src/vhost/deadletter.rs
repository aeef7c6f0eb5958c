//! Routing dead letters through a vhost: the dead letters a queue
//! operation returned (each already carrying its `x-death` history, see
//! `queue::leaving`) go to their dead-letter exchanges and on to queues.
//! This module sits beside the vhost and uses it and the queues; each copy
//! goes through the vhost's publish step (`publish`), which stores it as
//! it stores any publish.
//!
//! Routing is a work list, never recursion: a dead letter delivered to a
//! queue can make that queue dead-letter again (it is full, say), and those
//! letters join the list. Two rules bound the work. RabbitMQ's cycle rule:
//! a dead letter is not delivered to a queue it already died in unless a
//! client rejection is part of that cycle ([`closes_automatic_cycle`]).
//! And a budget: one original dead letter may give rise to at most
//! [`CASCADE_LIMIT`] further ones, so a topology that multiplies dead
//! letters (queues dead-lettering into a fanout exchange they are all
//! bound to) costs a bounded amount of work per message. That work is done
//! a queue per step, in slices (see `slice`).

use crate::queue::{DeadLetter, DeadLetters};
use crate::slice::{finish_in_background, Progress, Slice};
use crate::stats::DeadLetterStrategy;
use crate::vhost::publish::Publishing;
use crate::vhost::Vhost;
use leveret_protocol::{FieldValue, ShortStr};
use std::collections::VecDeque;
use std::sync::Arc;

/// How many dead letters one dead letter may cause in turn while it is
/// routed. RabbitMQ has no such limit; a real topology dead-letters a
/// message again at once only when it lands in a full queue, a handful of
/// times at most.
pub const CASCADE_LIMIT: usize = 256;

/// Routes `letters` through their dead-letter exchanges in `vhost`, with
/// the cycle rule and the cascade budget, one queue per step: the first
/// slice now, the rest in the background (a dead letter fanned out to
/// thousands of queues, or thousands of dead letters, do not hold the
/// thread).
pub fn route(vhost: &Arc<Vhost>, letters: DeadLetters) {
    if letters.is_empty() {
        return;
    }
    let mut routing = Routing {
        vhost: Arc::clone(vhost),
        originals: letters.into_iter(),
        work: VecDeque::new(),
        caused: 0,
        delivery: None,
        over_budget: 0,
    };
    finish_in_background(move |slice| routing.run(slice));
}

/// The state of [`route`] between slices.
struct Routing {
    vhost: Arc<Vhost>,
    originals: std::vec::IntoIter<DeadLetter>,
    /// The current original's letters still to route, breadth first.
    work: VecDeque<DeadLetter>,
    /// Letters the current original has caused so far.
    caused: usize,
    /// The copy being published to the queues it was routed to.
    delivery: Option<Publishing>,
    over_budget: usize,
}

impl Routing {
    fn run(&mut self, slice: &mut Slice) -> Progress {
        loop {
            if let Some(publishing) = &mut self.delivery {
                // Dead letters are at most once: no confirm waits for the
                // outcome, and flow control does not slow a dead-letterer.
                let progress = self.vhost.publish_step(publishing, slice);
                for next in publishing.take_dead_letters() {
                    if self.caused == CASCADE_LIMIT {
                        // Dead-lettered by its queue all the same;
                        // Leveret's budget drops it on the way.
                        count(&self.vhost, &next);
                        self.over_budget += 1;
                    } else {
                        self.caused += 1;
                        self.work.push_back(next);
                    }
                }
                if progress == Progress::More {
                    return Progress::More;
                }
                self.delivery = None;
            } else if let Some(letter) = self.work.pop_front() {
                self.delivery = start_delivery(&self.vhost, letter);
            } else if let Some(letter) = self.originals.next() {
                self.caused = 0;
                self.work.push_back(letter);
            } else {
                if self.over_budget > 0 {
                    tracing::warn!(
                        dropped = self.over_budget,
                        limit = CASCADE_LIMIT,
                        "dead letters causing too many further dead letters; the excess was dropped"
                    );
                }
                return Progress::Done;
            }
            if slice.step() {
                return Progress::More;
            }
        }
    }
}

/// Counts `letter` as RabbitMQ 3.10 does: `at_most_once` when its
/// dead-letter exchange exists, `disabled` (dropped) when it does not;
/// returns the exchange.
fn count(vhost: &Vhost, letter: &DeadLetter) -> Option<Arc<crate::exchange::Exchange>> {
    let exchange = vhost.exchange(letter.exchange());
    let strategy = match exchange {
        Some(_) => DeadLetterStrategy::AtMostOnce,
        None => DeadLetterStrategy::Disabled,
    };
    vhost.counters().dead_lettered(letter.reason(), strategy);
    exchange
}

/// The publish of one dead letter's copy to the queues its dead-letter
/// exchange routes it to, except those the cycle rule rules out; marked
/// for storage, as a publish is, when it is persistent and reaches
/// durable queues.
fn start_delivery(vhost: &Vhost, letter: DeadLetter) -> Option<Publishing> {
    let Some(exchange) = count(vhost, &letter) else {
        tracing::debug!(exchange = %letter.exchange(), "dead-letter exchange missing; message dropped");
        return None;
    };
    let (copy, headers) = letter.into_copy();
    let mut queues = Vec::new();
    vhost.route(
        &exchange,
        &copy.routing_key,
        Some(&headers),
        &mut queues,
        &mut None,
    );
    let deaths = match headers.get("x-death") {
        Some(FieldValue::Array(deaths)) => deaths.as_slice(),
        _ => &[],
    };
    queues.retain(|queue| {
        let cycle = closes_automatic_cycle(deaths, &queue.name);
        if cycle {
            tracing::warn!(queue = %queue.name, "dead-letter cycle detected; message dropped");
        }
        !cycle
    });
    let message = match vhost.storage(copy.persistent, &queues) {
        Some(stored) => Arc::new(copy.stored_as(Some(stored))),
        None => copy,
    };
    Some(Publishing::new(message, queues))
}

/// RabbitMQ's cycle rule. `deaths` is a dead letter's `x-death` history,
/// newest first (its latest death included). Delivering it to `queue`
/// closes a cycle if `queue` is in that history; the cycle is broken (the
/// delivery dropped) only if every death from the newest back to `queue`'s
/// is automatic (expired, maxlen): a client's rejection in the cycle, or an
/// entry the broker did not write, lets it continue.
pub fn closes_automatic_cycle(deaths: &[FieldValue], queue: &ShortStr) -> bool {
    let mut automatic = true;
    for entry in deaths {
        let FieldValue::Table(death) = entry else {
            automatic = false;
            continue;
        };
        if death.get("reason").and_then(FieldValue::as_bytes) == Some(b"rejected".as_slice()) {
            automatic = false;
        }
        if death.get("queue").and_then(FieldValue::as_bytes) == Some(queue.as_bytes()) {
            return automatic;
        }
    }
    false
}

#[cfg(test)]
mod tests {
    use super::*;

    fn s(v: &'static str) -> ShortStr {
        ShortStr::from_static(v)
    }

    fn death(queue: &'static str, reason: &'static str) -> FieldValue {
        FieldValue::Table(
            [
                (s("queue"), FieldValue::LongStr(s(queue).into_bytes())),
                (s("reason"), FieldValue::string(reason)),
            ]
            .into_iter()
            .collect(),
        )
    }

    #[test]
    fn a_queue_not_in_the_history_closes_no_cycle() {
        assert!(!closes_automatic_cycle(&[], &s("q")));
        assert!(!closes_automatic_cycle(&[death("a", "maxlen")], &s("q")));
    }

    #[test]
    fn automatic_deaths_back_to_the_queue_close_a_cycle() {
        assert!(closes_automatic_cycle(&[death("q", "maxlen")], &s("q")));
        let history = [death("b", "expired"), death("a", "maxlen")];
        assert!(closes_automatic_cycle(&history, &s("a")));
        assert!(closes_automatic_cycle(&history, &s("b")));
    }

    #[test]
    fn a_rejection_in_the_cycle_lets_it_continue() {
        assert!(!closes_automatic_cycle(&[death("q", "rejected")], &s("q")));
        let history = [death("b", "expired"), death("a", "rejected")];
        assert!(!closes_automatic_cycle(&history, &s("a")));
        // `b`'s cycle is only its own expiry: the older rejection is not in it.
        assert!(closes_automatic_cycle(&history, &s("b")));
        let history = [death("a", "rejected"), death("b", "expired")];
        assert!(!closes_automatic_cycle(&history, &s("b")));
    }

    #[test]
    fn an_entry_the_broker_did_not_write_lets_it_continue() {
        let history = [FieldValue::I64(7), death("a", "maxlen")];
        assert!(!closes_automatic_cycle(&history, &s("a")));
    }
}
