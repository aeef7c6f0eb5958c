//! Sequence tracking on the consumer side.
//!
//! For each publisher a consumer hears from, a [`SeqTracker`] keeps a
//! bitmap of the counters seen (duplicates, distinct count) and the
//! highest counter so far. Each delivery is then one of:
//! - in order: the next counter after the highest so far;
//! - a gap: further ahead than the next one (messages skipped, lost or
//!   taken by another consumer of the same queue);
//! - out of order: behind the highest so far, and not seen before;
//! - a duplicate: seen before.
//!
//! The paper's "arrival order errors" (any message that is not the next in
//! sequence) are gaps plus out-of-order arrivals; they only mean something
//! for a queue's sole consumer. Lost messages are counted per queue at the
//! end, as published minus distinct received.

use crate::body::split_seq;
use serde::Serialize;

#[derive(Debug, Clone, Default)]
struct PublisherTrack {
    /// Highest counter seen.
    highest: Option<u64>,
    bits: Vec<u64>,
}

/// Per-consumer sequence state.
#[derive(Debug, Clone, Default)]
pub struct SeqTracker {
    publishers: Vec<PublisherTrack>,
    counts: SeqCounts,
}

/// What a [`SeqTracker`] counted.
#[derive(Debug, Clone, Copy, Default, Serialize, PartialEq, Eq)]
pub struct SeqCounts {
    /// Deliveries.
    pub received: u64,
    /// Distinct messages (deliveries minus duplicates).
    pub distinct: u64,
    /// Arrivals further ahead than the next in sequence.
    pub gaps: u64,
    /// Arrivals behind one already received.
    pub out_of_order: u64,
    /// Messages received more than once.
    pub duplicates: u64,
    /// Bodies too short to carry a sequence number.
    pub unreadable: u64,
}

impl SeqCounts {
    /// The paper's arrival order errors: gaps plus out-of-order arrivals.
    pub fn order_errors(&self) -> u64 {
        self.gaps + self.out_of_order
    }

    /// Counts accumulated since `earlier`.
    pub fn since(&self, earlier: &SeqCounts) -> SeqCounts {
        SeqCounts {
            received: self.received - earlier.received,
            distinct: self.distinct - earlier.distinct,
            gaps: self.gaps - earlier.gaps,
            out_of_order: self.out_of_order - earlier.out_of_order,
            duplicates: self.duplicates - earlier.duplicates,
            unreadable: self.unreadable - earlier.unreadable,
        }
    }

    /// Adds another consumer's counts.
    pub fn add(&mut self, other: &SeqCounts) {
        self.received += other.received;
        self.distinct += other.distinct;
        self.gaps += other.gaps;
        self.out_of_order += other.out_of_order;
        self.duplicates += other.duplicates;
        self.unreadable += other.unreadable;
    }
}

impl SeqTracker {
    /// Records a delivery's sequence number (`None`: the body had none).
    #[inline]
    pub fn record(&mut self, seq: Option<u64>) {
        self.counts.received += 1;
        let Some(seq) = seq else {
            self.counts.unreadable += 1;
            return;
        };
        let (publisher, n) = split_seq(seq);
        let publisher = usize::from(publisher);
        if self.publishers.len() <= publisher {
            self.publishers
                .resize_with(publisher + 1, PublisherTrack::default);
        }
        let track = &mut self.publishers[publisher];
        let word = (n / 64) as usize;
        let bit = 1u64 << (n % 64);
        if track.bits.len() <= word {
            track.bits.resize((word + 1).next_power_of_two(), 0);
        }
        if track.bits[word] & bit != 0 {
            self.counts.duplicates += 1;
            return;
        }
        track.bits[word] |= bit;
        self.counts.distinct += 1;
        let expected = track.highest.map_or(0, |h| h + 1);
        if n > expected {
            self.counts.gaps += 1;
        } else if n < expected {
            self.counts.out_of_order += 1;
        }
        if track.highest.is_none_or(|h| n > h) {
            track.highest = Some(n);
        }
    }

    /// The counts so far.
    pub fn counts(&self) -> SeqCounts {
        self.counts
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::body::make_seq;

    #[test]
    fn classifies_arrivals() {
        let mut t = SeqTracker::default();
        for n in [0, 1, 2, 4, 3, 3, 5] {
            t.record(Some(make_seq(1, n)));
        }
        t.record(Some(make_seq(0, 0)));
        t.record(None);
        let c = t.counts();
        assert_eq!(c.received, 9);
        assert_eq!(c.distinct, 7);
        assert_eq!(c.gaps, 1);
        assert_eq!(c.out_of_order, 1);
        assert_eq!(c.duplicates, 1);
        assert_eq!(c.unreadable, 1);
        assert_eq!(c.order_errors(), 2);
    }

    #[test]
    fn a_late_start_is_a_gap() {
        let mut t = SeqTracker::default();
        t.record(Some(make_seq(0, 5)));
        assert_eq!(t.counts().gaps, 1);
    }
}
