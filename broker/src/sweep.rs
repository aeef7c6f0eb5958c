//! Expiry housekeeping: the sweeper task that drops expired messages
//! (x-message-ttl, per-message `expiration`) and deletes unused x-expires
//! queues, and the count that tells it whether there is anything to sweep.
//! A broker with no queue that can expire anything does not wake at all
//! (an idle robot's broker should not tick 20 times a second).

use crate::core::Core;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Duration;
use tokio::sync::Notify;

/// How many queues have something that may expire: messages with a TTL
/// waiting, or an x-expires argument.
#[derive(Debug, Default)]
pub struct SweepDemand {
    queues: AtomicUsize,
    wake: Notify,
}

impl SweepDemand {
    /// One more queue to sweep.
    pub fn add(&self) {
        if self.queues.fetch_add(1, Ordering::AcqRel) == 0 {
            self.wake.notify_one();
        }
    }

    /// One queue fewer.
    pub fn sub(&self) {
        self.queues.fetch_sub(1, Ordering::AcqRel);
    }

    /// Returns once some queue needs sweeping.
    async fn wanted(&self) {
        loop {
            let woken = self.wake.notified();
            if self.queues.load(Ordering::Acquire) > 0 {
                return;
            }
            woken.await;
        }
    }
}

/// Every `period` while some queue needs it: expires messages and unused
/// queues in every vhost.
pub async fn sweeper(core: Arc<Core>, period: Duration) {
    let mut shutdown = core.shutdown_signal();
    let mut ticker = tokio::time::interval(period);
    ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            _ = async { core.sweep_demand.wanted().await; ticker.tick().await } => {}
            _ = shutdown.wait_for(|down| *down) => return,
        }
        for vhost in core.vhosts() {
            vhost.sweep();
        }
    }
}
