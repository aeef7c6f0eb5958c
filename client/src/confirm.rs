//! Publisher confirms: after `confirm.select`, every publish on the channel
//! gets the next sequence number and a [`PublishConfirm`] future that
//! resolves when the broker's `basic.ack` or `basic.nack` (possibly
//! `multiple`) covers it. [`Confirms`] is the channel's table of
//! outstanding numbers, kept in publish order.

use crate::error::{Error, Result};
use std::collections::VecDeque;
use std::future::{Future, IntoFuture};
use std::pin::Pin;
use std::task::{Context, Poll};
use tokio::sync::oneshot;

/// The broker's answer to one publish.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Confirmation {
    /// The broker took responsibility for the message (`basic.ack`).
    Ack,
    /// The broker could not take it (`basic.nack`), e.g. a full queue with
    /// `x-overflow: reject-publish`.
    Nack,
    /// The channel is not in confirm mode: nothing to wait for.
    NotRequested,
}

impl Confirmation {
    /// Whether this is [`Confirmation::Ack`].
    pub fn is_ack(self) -> bool {
        self == Confirmation::Ack
    }
}

/// The handle on one publish's confirmation: `.await` it for the
/// broker's [`Confirmation`], or the error that closed the channel first.
/// Ignoring or dropping it is fine: the publish still counts for
/// `Channel::wait_for_confirms`.
#[derive(Debug)]
pub struct PublishConfirm {
    rx: Option<oneshot::Receiver<Result<Confirmation>>>,
}

impl PublishConfirm {
    pub(crate) fn not_requested() -> Self {
        PublishConfirm { rx: None }
    }

    pub(crate) fn pending(rx: oneshot::Receiver<Result<Confirmation>>) -> Self {
        PublishConfirm { rx: Some(rx) }
    }

    /// Whether the channel was in confirm mode for this publish.
    pub fn is_requested(&self) -> bool {
        self.rx.is_some()
    }
}

impl IntoFuture for PublishConfirm {
    type Output = Result<Confirmation>;
    type IntoFuture = ConfirmFuture;

    fn into_future(self) -> ConfirmFuture {
        ConfirmFuture {
            rx: self.rx,
            answer: None,
        }
    }
}

/// The future of a [`PublishConfirm`].
#[derive(Debug)]
pub struct ConfirmFuture {
    rx: Option<oneshot::Receiver<Result<Confirmation>>>,
    /// The answer [`ConfirmFuture::try_answer`] found, for the future to
    /// resolve to.
    answer: Option<Result<Confirmation>>,
}

impl ConfirmFuture {
    /// The broker's answer if it has come, without waiting and without
    /// taking the place of the waker a poll left (a task waiting on this
    /// future is still woken by the answer): for a publisher that looks
    /// before it would wait, as for an in-process publish, whose confirm
    /// has come by the time `basic_publish` returns when the broker
    /// handled it on the publishing thread. The future then resolves to
    /// the same answer.
    pub fn try_answer(&mut self) -> Option<Result<Confirmation>> {
        if let Some(answer) = &self.answer {
            return Some(answer.clone());
        }
        let answer = match &mut self.rx {
            None => Ok(Confirmation::NotRequested),
            Some(rx) => match rx.try_recv() {
                Ok(answer) => answer,
                Err(oneshot::error::TryRecvError::Empty) => return None,
                Err(oneshot::error::TryRecvError::Closed) => Err(Error::Closed),
            },
        };
        self.answer = Some(answer.clone());
        Some(answer)
    }
}

impl Future for ConfirmFuture {
    type Output = Result<Confirmation>;

    fn poll(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<Self::Output> {
        let this = self.get_mut();
        if let Some(answer) = this.answer.take() {
            return Poll::Ready(answer);
        }
        match &mut this.rx {
            None => Poll::Ready(Ok(Confirmation::NotRequested)),
            Some(rx) => Pin::new(rx)
                .poll(cx)
                .map(|result| result.unwrap_or(Err(Error::Closed))),
        }
    }
}

/// A channel's outstanding confirms.
#[derive(Debug)]
pub(crate) struct Confirms {
    next: u64,
    pending: VecDeque<(u64, oneshot::Sender<Result<Confirmation>>)>,
    /// False once a nack arrived since the last `wait_for_confirms`.
    all_acked: bool,
}

impl Confirms {
    pub(crate) fn new() -> Self {
        Confirms {
            next: 1,
            pending: VecDeque::new(),
            all_acked: true,
        }
    }

    /// Numbers the next publish.
    pub(crate) fn register(&mut self) -> PublishConfirm {
        let (tx, rx) = oneshot::channel();
        self.pending.push_back((self.next, tx));
        self.next += 1;
        PublishConfirm::pending(rx)
    }

    /// Applies a `basic.ack` or `basic.nack`; true if nothing is
    /// outstanding afterwards.
    pub(crate) fn settle(&mut self, tag: u64, multiple: bool, ack: bool) -> bool {
        let answer = if ack {
            Confirmation::Ack
        } else {
            self.all_acked = false;
            Confirmation::Nack
        };
        if multiple {
            // Tag 0 with multiple: everything outstanding.
            while let Some((seq, _)) = self.pending.front() {
                if tag != 0 && *seq > tag {
                    break;
                }
                if let Some((_, tx)) = self.pending.pop_front() {
                    let _ = tx.send(Ok(answer));
                }
            }
        } else if let Ok(index) = self.pending.binary_search_by_key(&tag, |(seq, _)| *seq) {
            if let Some((_, tx)) = self.pending.remove(index) {
                let _ = tx.send(Ok(answer));
            }
        }
        self.pending.is_empty()
    }

    /// Fails everything outstanding.
    pub(crate) fn fail(&mut self, error: &Error) {
        for (_, tx) in self.pending.drain(..) {
            let _ = tx.send(Err(error.clone()));
        }
    }

    /// `Some(all acked since last time)` if nothing is outstanding.
    pub(crate) fn take_if_settled(&mut self) -> Option<bool> {
        if self.pending.is_empty() {
            Some(std::mem::replace(&mut self.all_acked, true))
        } else {
            None
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn single_and_multiple_settle_in_order() {
        let mut confirms = Confirms::new();
        let mut futures: Vec<_> = (0..5).map(|_| confirms.register()).collect();
        assert!(!confirms.settle(2, false, true));
        assert!(!confirms.settle(3, true, false));
        assert!(confirms.settle(5, true, true));
        let answers: Vec<_> = futures
            .iter_mut()
            .map(|f| f.rx.as_mut().unwrap().try_recv().unwrap().unwrap())
            .collect();
        use Confirmation::*;
        assert_eq!(answers, [Nack, Ack, Nack, Ack, Ack]);
        assert_eq!(confirms.take_if_settled(), Some(false));
        assert_eq!(confirms.take_if_settled(), Some(true));
    }

    #[test]
    fn an_answer_looked_at_is_what_the_future_resolves_to() {
        let mut confirms = Confirms::new();
        let mut first = confirms.register().into_future();
        let mut second = confirms.register().into_future();
        assert!(first.try_answer().is_none(), "not settled yet");
        confirms.settle(1, false, false);
        assert!(matches!(first.try_answer(), Some(Ok(Confirmation::Nack))));
        assert!(matches!(first.try_answer(), Some(Ok(Confirmation::Nack))));
        let mut context = Context::from_waker(std::task::Waker::noop());
        assert!(matches!(
            Pin::new(&mut first).poll(&mut context),
            Poll::Ready(Ok(Confirmation::Nack))
        ));
        confirms.fail(&Error::Closed);
        assert!(matches!(second.try_answer(), Some(Err(Error::Closed))));
        let mut unrequested = PublishConfirm::not_requested().into_future();
        assert!(matches!(
            unrequested.try_answer(),
            Some(Ok(Confirmation::NotRequested))
        ));
    }

    #[test]
    fn multiple_with_tag_zero_settles_everything() {
        let mut confirms = Confirms::new();
        let _a = confirms.register();
        let _b = confirms.register();
        assert!(confirms.settle(0, true, true));
    }
}
