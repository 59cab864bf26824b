//! Times the stages of the pipeline from its `tracing` spans (Marknet's `marknet.*`, the stereo
//! session's `track`, `triangulate`, `outliers`, `contact`, `slip`): [`SpanClock`] is a subscriber that
//! the latency mode installs on its own thread only, and that sums, per span name and frame, the wall
//! time and the process CPU time between the span's enter and exit, less the time of the spans nested
//! in it (a span's own time, as a flame graph shows it).

use std::sync::{Mutex, MutexGuard, PoisonError};
use std::time::Instant;

use tracing::span::{Attributes, Id, Record};
use tracing::{Event, Metadata, Subscriber};

use super::process_cpu_clock_ns;

/// A point in time and the process CPU time then.
#[derive(Debug, Clone, Copy)]
pub(super) struct Mark {
    wall: Instant,
    cpu_ns: Option<u64>,
}

impl Mark {
    pub(super) fn now() -> Self {
        let cpu_ns = process_cpu_clock_ns();
        Self {
            wall: Instant::now(),
            cpu_ns,
        }
    }
}

/// Wall and process CPU time, ns.
#[derive(Debug, Clone, Copy)]
pub(super) struct Interval {
    wall_ns: u64,
    /// `None` when a clock reading failed.
    cpu_ns: Option<u64>,
}

impl Interval {
    const ZERO: Self = Self {
        wall_ns: 0,
        cpu_ns: Some(0),
    };

    pub(super) fn between(start: &Mark, end: &Mark) -> Self {
        let wall = end.wall.saturating_duration_since(start.wall);
        Self {
            wall_ns: u64::try_from(wall.as_nanos()).unwrap_or(u64::MAX),
            cpu_ns: start.cpu_ns.zip(end.cpu_ns).map(|(a, z)| z.saturating_sub(a)),
        }
    }

    pub(super) fn wall_ms(&self) -> f64 {
        self.wall_ns as f64 * 1e-6
    }

    /// CPU time, ms, less `overhead_ns` (the cost of one clock reading).
    pub(super) fn cpu_ms(&self, overhead_ns: u64) -> Option<f64> {
        self.cpu_ns.map(|c| c.saturating_sub(overhead_ns) as f64 * 1e-6)
    }

    fn add(&mut self, other: Self) {
        self.wall_ns += other.wall_ns;
        self.cpu_ns = self.cpu_ns.zip(other.cpu_ns).map(|(a, b)| a + b);
    }

    fn less(self, nested: Self) -> Self {
        Self {
            wall_ns: self.wall_ns.saturating_sub(nested.wall_ns),
            cpu_ns: self.cpu_ns.zip(nested.cpu_ns).map(|(a, b)| a.saturating_sub(b)),
        }
    }
}

/// One span name's times in a frame.
#[derive(Debug, Clone, Copy)]
pub(super) struct SpanTime {
    /// When a span of the name was first entered in the frame.
    pub(super) first: Mark,
    /// The own time of all its spans in the frame.
    pub(super) own: Interval,
}

/// A span entered and not yet left.
struct Open {
    name: usize,
    entered: Mark,
    nested: Interval,
}

#[derive(Default)]
struct State {
    /// Span names in order of appearance; a span's id is its name's index + 1.
    names: Vec<&'static str>,
    /// Per name, its times since the last [`SpanClock::take_frame`].
    frame: Vec<Option<SpanTime>>,
    open: Vec<Open>,
}

/// The subscriber (see the module docs). Every span of one name shares one id: the pipeline's
/// spans never nest in one of their own name, and only the name's totals are kept.
#[derive(Default)]
pub(super) struct SpanClock {
    state: Mutex<State>,
}

impl SpanClock {
    fn state(&self) -> MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// The times per span name since the last call, and a fresh start.
    pub(super) fn take_frame(&self) -> FrameSpans {
        let mut state = self.state();
        let names = state.names.clone();
        let times = state.frame.iter_mut().map(Option::take);
        FrameSpans(names.into_iter().zip(times).collect())
    }
}

/// [`SpanClock::take_frame`]'s times.
pub(super) struct FrameSpans(Vec<(&'static str, Option<SpanTime>)>);

impl FrameSpans {
    /// The times of the spans named `name`; `None` if none was entered.
    pub(super) fn get(&self, name: &str) -> Option<SpanTime> {
        self.0.iter().find(|(n, _)| *n == name).and_then(|(_, t)| *t)
    }
}

impl Subscriber for SpanClock {
    fn enabled(&self, metadata: &Metadata<'_>) -> bool {
        metadata.is_span()
    }

    fn new_span(&self, span: &Attributes<'_>) -> Id {
        let name = span.metadata().name();
        let mut state = self.state();
        let index = match state.names.iter().position(|n| *n == name) {
            Some(i) => i,
            None => {
                state.names.push(name);
                state.frame.push(None);
                state.names.len() - 1
            }
        };
        Id::from_u64(index as u64 + 1)
    }

    fn record(&self, _span: &Id, _values: &Record<'_>) {}

    fn record_follows_from(&self, _span: &Id, _follows: &Id) {}

    fn event(&self, _event: &Event<'_>) {}

    fn enter(&self, span: &Id) {
        let name = (span.into_u64() - 1) as usize;
        let entered = Mark::now();
        let mut state = self.state();
        if let Some(slot @ None) = state.frame.get_mut(name) {
            *slot = Some(SpanTime {
                first: entered,
                own: Interval::ZERO,
            });
        }
        state.open.push(Open {
            name,
            entered,
            nested: Interval::ZERO,
        });
    }

    fn exit(&self, span: &Id) {
        let name = (span.into_u64() - 1) as usize;
        let left = Mark::now();
        let mut state = self.state();
        let Some(at) = state.open.iter().rposition(|o| o.name == name) else {
            return;
        };
        let open = state.open.remove(at);
        let whole = Interval::between(&open.entered, &left);
        if let Some(Some(t)) = state.frame.get_mut(name) {
            t.own.add(whole.less(open.nested));
        }
        if let Some(parent) = state.open.last_mut() {
            parent.nested.add(whole);
        }
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;
    use std::time::Duration;

    use super::*;

    fn sleep_ms(ms: u64) {
        std::thread::sleep(Duration::from_millis(ms));
    }

    /// Marknet's post-process row is its call's own time: the network passes nested in it must not
    /// count twice. Sleeps only bound a time from below, so the checks leave a wide margin above.
    #[test]
    fn a_span_counts_its_own_time_without_the_spans_nested_in_it() {
        let clock = Arc::new(SpanClock::default());
        let _installed = tracing::subscriber::set_default(Arc::clone(&clock));
        tracing::trace_span!("outer").in_scope(|| {
            sleep_ms(5);
            tracing::trace_span!("inner").in_scope(|| sleep_ms(50));
            tracing::trace_span!("inner").in_scope(|| sleep_ms(50));
        });
        let frame = clock.take_frame();
        let (Some(outer), Some(inner)) = (frame.get("outer"), frame.get("inner")) else {
            panic!("a span was not timed");
        };
        assert!(inner.own.wall_ms() >= 100.0, "{}", inner.own.wall_ms());
        assert!(
            (5.0..100.0).contains(&outer.own.wall_ms()),
            "{}",
            outer.own.wall_ms()
        );
        assert!(outer.first.wall <= inner.first.wall);
        assert!(
            clock.take_frame().get("outer").is_none(),
            "the frame was not reset"
        );
    }

    /// The subscriber times the benchmark's thread only: the throughput mode's localizers run on
    /// worker threads.
    #[test]
    fn spans_of_other_threads_are_not_timed() {
        let clock = Arc::new(SpanClock::default());
        let _installed = tracing::subscriber::set_default(Arc::clone(&clock));
        std::thread::spawn(|| tracing::trace_span!("elsewhere").in_scope(|| sleep_ms(1)))
            .join()
            .unwrap_or_default();
        tracing::trace_span!("here").in_scope(|| sleep_ms(1));
        let frame = clock.take_frame();
        assert!(frame.get("elsewhere").is_none());
        assert!(frame.get("here").is_some());
    }
}
