//! The order in which queued work is served: one queue per flow (a tenant on a device), served by weighted fair
//! queuing on time. Each flow has a virtual `pass`; serving a task advances its flow's pass by the task's time
//! divided by the flow's share, and the flow with the smallest pass is served next. A flow that was idle starts at
//! the current virtual time, so idleness earns no credit and a newcomer waits at most for the tasks already being
//! served.
//!
//! A task is charged its estimated time when it is served, and the difference once it ran ([`FairQueue::settle`]):
//! two flows with equal shares get equal time of the workers, whatever their rays cost. A flow of rays a thousand
//! times costlier than another's is then served a thousandth of the rays, not as many (which would leave the other
//! flow the costly flow's ray rate), and a flow that sends one ray at a time is still served ahead of a flow with a
//! million queued.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Duration;

/// Who queued a task, and its weight.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Flow {
    /// The tenant's name.
    pub name: Arc<str>,
    /// Its weight: a flow with share 2 is served twice the time of a flow with share 1 while both have work.
    pub share: u32,
}

/// One flow's queue and place in virtual time.
#[derive(Debug)]
struct FlowQueue<T> {
    /// Virtual time at which its next task starts (nanoseconds of a worker, divided by the share).
    pass: f64,
    /// The flow's share, as last pushed.
    share: f64,
    /// Its tasks served and not yet settled: a flow with one running is not idle.
    running: usize,
    /// Its waiting tasks with their estimated times (nanoseconds), by their order and then by arrival.
    tasks: BTreeMap<(u64, u64), (f64, T)>,
}

/// What a served task was charged: its estimate, settled once the task ran ([`FairQueue::settle`]).
#[derive(Debug)]
#[must_use = "a charge is settled with the time the task took"]
pub struct Charge {
    /// The flow charged.
    flow: Arc<str>,
    /// Its share.
    share: f64,
    /// The task's estimated time, in nanoseconds.
    estimate: f64,
}

/// Tasks of many flows, taken out fairly.
#[derive(Debug)]
pub struct FairQueue<T> {
    /// Every flow seen, by name (ordered, so ties are broken the same way every time).
    flows: BTreeMap<Arc<str>, FlowQueue<T>>,
    /// The virtual time: the start of the task served last.
    now: f64,
    /// Tasks waiting in all flows.
    len: usize,
    /// Tasks pushed so far: the arrival number of the next.
    pushed: u64,
}

impl<T> Default for FairQueue<T> {
    fn default() -> Self {
        FairQueue { flows: BTreeMap::new(), now: 0.0, len: 0, pushed: 0 }
    }
}

impl<T> FairQueue<T> {
    /// Whether no task waits.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// Tasks waiting.
    pub fn len(&self) -> usize {
        self.len
    }

    /// Queues `task`, estimated to take `estimate` of a worker's time, among the tasks of `flow`: behind those of the
    /// same or a smaller `order`, ahead of those of a larger one (a trace's pieces, queued one at a time, all have
    /// its order: the trace's arrival, so that a flow's traces are served in arrival order).
    pub fn push(&mut self, flow: &Flow, order: u64, estimate: Duration, task: T) {
        let now = self.now;
        let queue = self.flows.entry(Arc::clone(&flow.name)).or_insert_with(|| FlowQueue {
            pass: now,
            share: 1.0,
            running: 0,
            tasks: BTreeMap::new(),
        });
        if queue.tasks.is_empty() && queue.running == 0 {
            queue.pass = queue.pass.max(now);
        }
        queue.share = f64::from(flow.share.max(1));
        queue.tasks.insert((order, self.pushed), (estimate.as_nanos() as f64, task));
        self.pushed += 1;
        self.len += 1;
    }

    /// Takes the next task: the first waiting one of the flow whose pass is smallest, charged its estimate; the
    /// charge is settled once it ran.
    pub fn pop(&mut self) -> Option<(T, Charge)> {
        let (name, queue) =
            self.flows.iter_mut().filter(|(_, q)| !q.tasks.is_empty()).min_by(|a, b| a.1.pass.total_cmp(&b.1.pass))?;
        let (_, (estimate, task)) = queue.tasks.pop_first()?;
        self.now = queue.pass;
        queue.pass += estimate / queue.share;
        queue.running += 1;
        self.len -= 1;
        Some((task, Charge { flow: Arc::clone(name), share: queue.share, estimate }))
    }

    /// Charges a served task's flow the time the task `took` instead of its estimate.
    pub fn settle(&mut self, charge: Charge, took: Duration) {
        if let Some(queue) = self.flows.get_mut(&charge.flow) {
            queue.pass += (took.as_nanos() as f64 - charge.estimate) / charge.share;
            queue.running -= 1;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn flow(name: &str, share: u32) -> Flow {
        Flow { name: name.into(), share }
    }

    /// Serves the next task, which takes just its estimate.
    fn serve(queue: &mut FairQueue<&'static str>) -> Option<&'static str> {
        let (task, charge) = queue.pop()?;
        let took = Duration::from_nanos(charge.estimate as u64);
        queue.settle(charge, took);
        Some(task)
    }

    /// Serves everything and returns the flow names in the order served.
    fn drain(queue: &mut FairQueue<&'static str>) -> Vec<&'static str> {
        std::iter::from_fn(|| serve(queue)).collect()
    }

    fn micros(n: u64) -> Duration {
        Duration::from_micros(n)
    }

    #[test]
    fn a_newcomer_is_served_next_however_much_another_flow_has_queued() {
        let mut queue = FairQueue::default();
        let flood = flow("a", 1);
        for _ in 0..1000 {
            queue.push(&flood, 0, micros(1024), "a");
        }
        for _ in 0..10 {
            assert_eq!(serve(&mut queue), Some("a"));
        }
        queue.push(&flow("b", 1), 0, micros(1), "b");
        assert_eq!(serve(&mut queue), Some("b"), "one ray of b goes before the rest of a's million");
        assert_eq!(queue.len(), 990);
    }

    #[test]
    fn busy_flows_get_time_in_proportion_to_their_shares() {
        let mut queue = FairQueue::default();
        let (a, b) = (flow("a", 1), flow("b", 3));
        for _ in 0..400 {
            queue.push(&a, 0, micros(100), "a");
            queue.push(&b, 0, micros(100), "b");
        }
        let first: Vec<_> = drain(&mut queue).into_iter().take(400).collect();
        let served_b = first.iter().filter(|&&n| n == "b").count();
        assert!((299..=301).contains(&served_b), "b has 3 of 4 shares: {served_b} of 400");
    }

    #[test]
    fn equal_shares_split_time_not_tasks() {
        let mut queue = FairQueue::default();
        let (big, small) = (flow("big", 1), flow("small", 1));
        for _ in 0..100 {
            queue.push(&big, 0, micros(1000), "big");
        }
        for _ in 0..1000 {
            queue.push(&small, 0, micros(100), "small");
        }
        // While both have work, each gets about half the time: one big task for every ten small ones.
        let order = drain(&mut queue);
        let window = &order[..550];
        let big_time = window.iter().filter(|&&n| n == "big").count() * 1000;
        let small_time = window.iter().filter(|&&n| n == "small").count() * 100;
        assert!(big_time.abs_diff(small_time) <= 1000, "{big_time} against {small_time}");
    }

    #[test]
    fn a_flow_is_charged_the_time_its_tasks_took_not_their_estimates() {
        // Both flows' tasks are estimated at 1 ms; a's take 10 ms, b's 1 ms.
        let mut queue = FairQueue::default();
        let (a, b) = (flow("a", 1), flow("b", 1));
        for _ in 0..100 {
            queue.push(&a, 0, micros(1000), "a");
            queue.push(&b, 0, micros(1000), "b");
        }
        let mut time = [0u64; 2];
        while time.iter().sum::<u64>() < 100_000 {
            let (task, charge) = queue.pop().unwrap();
            let took = micros(if task == "a" { 10_000 } else { 1000 });
            queue.settle(charge, took);
            time[usize::from(task == "b")] += took.as_micros() as u64;
        }
        // Each got about half the time: a a tenth of b's tasks (a charge by estimate would have split tasks evenly).
        assert!(time[0].abs_diff(time[1]) <= 11_000, "a {} µs, b {} µs", time[0], time[1]);
    }

    #[test]
    fn idle_time_earns_no_credit() {
        let mut queue = FairQueue::default();
        let (a, b) = (flow("a", 1), flow("b", 1));
        queue.push(&b, 0, micros(10), "b");
        assert_eq!(serve(&mut queue), Some("b"));
        for _ in 0..100 {
            queue.push(&a, 0, micros(10), "a");
        }
        for _ in 0..50 {
            serve(&mut queue);
        }
        // b was idle while a was served 50 times: it now alternates with a instead of running 50 in a row.
        for _ in 0..10 {
            queue.push(&b, 0, micros(10), "b");
        }
        let next: Vec<_> = drain(&mut queue).into_iter().take(20).collect();
        let run_of_b = next.iter().take_while(|&&n| n == "b").count();
        assert!(run_of_b <= 1, "{next:?}");
        assert_eq!(next.iter().filter(|&&n| n == "b").count(), 10, "{next:?}");
    }

    #[test]
    fn one_flow_keeps_its_order() {
        let mut queue = FairQueue::default();
        let a = flow("a", 5);
        for name in ["1", "2", "3"] {
            queue.push(&a, 0, micros(7), name);
        }
        assert_eq!(drain(&mut queue), ["1", "2", "3"]);
        assert!(queue.is_empty());
    }

    #[test]
    fn a_later_task_of_an_earlier_order_goes_first_within_its_flow() {
        // Trace 1's second piece is queued after trace 2's first: it is still served first.
        let mut queue = FairQueue::default();
        let a = flow("a", 1);
        queue.push(&a, 1, micros(7), "1a");
        assert_eq!(serve(&mut queue), Some("1a"));
        queue.push(&a, 2, micros(7), "2a");
        queue.push(&a, 1, micros(7), "1b");
        queue.push(&a, 2, micros(7), "2b");
        assert_eq!(drain(&mut queue), ["1b", "2a", "2b"]);
    }

    #[test]
    fn a_flow_with_a_task_running_is_not_idle() {
        // a's task, estimated at 1 ms, runs 10 ms; meanwhile b is served and a queues another task. a was busy all
        // along, so it is charged the 10 ms once, from where its pass stood, not from the virtual time b reached.
        let mut queue = FairQueue::default();
        let (a, b) = (flow("a", 1), flow("b", 1));
        queue.push(&a, 0, micros(1000), "a");
        let (_, running) = queue.pop().unwrap();
        for _ in 0..5 {
            queue.push(&b, 0, micros(1000), "b");
            serve(&mut queue);
        }
        queue.push(&a, 0, micros(1000), "a");
        queue.settle(running, micros(10_000));
        assert_eq!(queue.flows["a"].pass, 10e6, "charged 10 ms from 0");
    }
}
