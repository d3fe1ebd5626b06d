//! Runs a checked pipeline: one thread per stage, bounded channels between them.
//!
//! The imaging loop (network step <-> residual update) is a cycle of bounded channels, which
//! could deadlock if it filled up; admission tokens keep at most `channel_capacity` jobs
//! inside a loop, so a send inside the loop always finds room. A stage ends when its input is
//! empty, every stage feeding it from outside the loop has ended, and its loop (if any) holds
//! no job. The first stage error (or the caller's cancel flag) stops every stage; the error
//! names the stage and job. The stop is the run's own (`super::cancel`): the caller's flag is
//! only read, so a failed or cancelled run leaves nothing set for the next. A source error (an
//! unreadable input) stops the reading but lets the jobs already in the pipeline finish, since
//! they do not depend on it.

use super::cancel::RunStop;
use super::config::PipelineSpec;
use super::graph::Graph;
use super::registry::{check_products, BuildContext, Built, Registry, Role};
use super::stage::{Payload, Port};
use crate::{Error, Result};
use crossbeam_channel::{bounded, Receiver, RecvTimeoutError, Sender};
use std::collections::BTreeMap;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// What a finished run did.
#[derive(Clone, Debug, Default)]
pub struct RunReport {
    /// Ids of the jobs that reached a writer, in completion order.
    pub jobs: Vec<String>,
    pub seconds: f64,
    /// Seconds per stage, summed over jobs (stage name -> seconds): work only, not the time
    /// spent waiting for room in the next stage's channel.
    pub stage_seconds: BTreeMap<String, f64>,
    /// The files each job's sinks wrote (job id -> paths), where the payload's sinks record
    /// them (the engine's writers do).
    pub written: BTreeMap<String, Vec<std::path::PathBuf>>,
}

const POLL: Duration = Duration::from_millis(20);

/// What the stages are doing, reported to the caller's observer as it happens (the CLI draws
/// a progress bar from it; the runner draws nothing).
#[derive(Clone, Debug)]
pub enum Progress {
    /// `stage` started on `job` (`iteration`: network steps done so far, `of`: planned, 0 when
    /// not known).
    Working { stage: String, job: String, iteration: usize, of: usize },
    /// `stage` finished its job and waits for the next.
    Idle { stage: String },
    /// `job` reached the end of the pipeline.
    Finished { job: String },
}

/// Check and build every stage without running anything (`r2d2 validate`).
pub fn validate<J: Payload>(registry: &Registry<J>, config: &PipelineSpec, context: &J::Context) -> Result<Graph> {
    let graph = Graph::build(registry, config)?;
    let stop = RunStop::new();
    let _in = stop.enter();
    build_all(registry, config, &graph, context, true)?;
    Ok(graph)
}

/// Run the pipeline to completion, or until `cancel` turns true, reporting to `progress`.
/// `cancel` is only read: the run stops itself without setting it.
pub fn run<J: Payload>(
    registry: &Registry<J>,
    config: &PipelineSpec,
    context: &J::Context,
    cancel: Arc<AtomicBool>,
    progress: &(dyn Fn(&Progress) + Sync),
) -> Result<RunReport> {
    let graph = Graph::build(registry, config)?;
    let stop = RunStop::new();
    let built = {
        // Parts built now (a plugin host) register with this run's stop.
        let _in = stop.enter();
        build_all(registry, config, &graph, context, false)?
    };
    run_built(config, &graph, built, &stop, &cancel, progress)
}

/// Checks what each stage consumes against what the stages before it produce, then builds
/// every stage (in file order), telling each what the stages after it consume.
fn build_all<J: Payload>(registry: &Registry<J>, config: &PipelineSpec, graph: &Graph, context: &J::Context, validating: bool) -> Result<Vec<Built<J>>> {
    let reach = graph.reach();
    let context = |i: usize, downstream| {
        let (upstream_stages, downstream_stages) = neighbours(&reach, i);
        BuildContext { pipeline: config, stage: &config.stages[i], threads: config.threads, downstream, upstream_stages, downstream_stages, context, registry, validating }
    };
    let mut consumes = Vec::new();
    let mut produces = Vec::new();
    for (i, stage) in config.stages.iter().enumerate() {
        let kind = registry.kind_of(config, stage)?;
        consumes.push(kind.consumes(&context(i, Vec::new()))?);
        produces.push(kind.produces());
    }
    let downstream = check_products(config, &reach, &consumes, &produces)?;
    config
        .stages
        .iter()
        .zip(downstream)
        .enumerate()
        .map(|(i, (stage, downstream))| registry.kind_of(config, stage)?.build(&context(i, downstream)))
        .collect()
}

/// The stages whose jobs reach stage `i`, and those its jobs reach (loop edges included).
pub(crate) fn neighbours(reach: &[Vec<bool>], i: usize) -> (Vec<usize>, Vec<usize>) {
    let n = reach.len();
    ((0..n).filter(|&j| j != i && reach[j][i]).collect(), (0..n).filter(|&j| j != i && reach[i][j]).collect())
}

/// Runs stages already built (one per stage of `config`, in file order) along `graph`.
fn run_built<J: Payload>(
    config: &PipelineSpec,
    graph: &Graph,
    built: Vec<Built<J>>,
    stop: &RunStop,
    requested: &AtomicBool,
    progress: &(dyn Fn(&Progress) + Sync),
) -> Result<RunReport> {
    if requested.load(Ordering::SeqCst) {
        stop.stop();
    }
    let n = built.len();
    let cap = config.channel_capacity;
    let channels: Vec<(Sender<J>, Receiver<J>)> = (0..n).map(|_| bounded(cap)).collect();
    // Loop tokens, per step stage that heads a loop.
    let tokens: Vec<Option<(Sender<()>, Receiver<()>)>> = (0..n)
        .map(|i| {
            let heads_loop = graph.roles[i] == Role::Step && graph.next[i].is_some_and(|r| graph.is_loop_back(r, i));
            heads_loop.then(|| {
                let (tx, rx) = bounded(cap);
                for _ in 0..cap {
                    tx.send(()).expect("fresh channel has room");
                }
                (tx, rx)
            })
        })
        .collect();
    // Stages feeding each stage from outside a loop.
    let upstream: Vec<Vec<usize>> = (0..n)
        .map(|j| {
            (0..n)
                .filter(|&i| (graph.next[i] == Some(j) || graph.done[i] == Some(j)) && !graph.is_loop_back(i, j))
                .collect()
        })
        .collect();
    let ended: Vec<AtomicBool> = (0..n).map(|_| AtomicBool::new(false)).collect();
    let first_error: Mutex<Option<Error>> = Mutex::new(None);
    let finished: Mutex<Vec<String>> = Mutex::new(Vec::new());
    let totals: Mutex<BTreeMap<String, f64>> = Mutex::new(BTreeMap::new());
    let start = Instant::now();
    let record = |e: Error| {
        let mut slot = first_error.lock().expect("error slot");
        if slot.is_none() {
            *slot = Some(e);
        }
    };
    let fail = |e: Error| {
        record(e);
        stop.stop();
    };
    let stopped = || stop.is_stopped();

    std::thread::scope(|scope| {
        // Threads are started fallibly: under an address-space limit (`ulimit -v`) a thread's
        // stack may not fit, and `scope.spawn` would panic with the other stages waiting.
        let no_thread = |what: String, e: std::io::Error| {
            fail(Error::OutOfMemory(format!(
                "cannot start the thread of {what}: {e} (is the address space limited? ulimit -v)"
            )));
        };
        // Turns the caller's request into this run's stop (which kills plugin hosts at once).
        let watcher = std::thread::Builder::new().name("r2d2-stop".into()).spawn_scoped(scope, || {
            while !ended.iter().all(|e| e.load(Ordering::SeqCst)) {
                if requested.load(Ordering::SeqCst) {
                    stop.stop();
                }
                std::thread::sleep(POLL);
            }
        });
        if let Err(e) = watcher {
            no_thread("the stop watcher".into(), e);
        }
        for (i, stage) in built.into_iter().enumerate() {
            if stop.is_stopped() {
                // A thread could not be started: the stages not yet started never run.
                ended[i].store(true, Ordering::SeqCst);
                continue;
            }
            let (config, graph, channels, tokens, upstream, ended) = (config, graph, &channels, &tokens, &upstream, &ended);
            let (stopped, fail, record, finished, totals) = (&stopped, &fail, &record, &finished, &totals);
            let spawned = std::thread::Builder::new().name(format!("r2d2-stage-{i}")).spawn_scoped(scope, move || {
                let _in = stop.enter();
                // However this thread ends, the stages downstream must not wait for it.
                let _ended = EndedOnExit { ended: &ended[i], stop };
                let name = &config.stages[i].name;
                let kind = &config.stages[i].kind;
                // Send on a port, taking a loop token when entering a loop from outside and
                // giving it back when leaving the loop through `done`.
                let send = |port: Port, mut job: J, began: Instant| -> Result<()> {
                    // Work time only: waiting below for room downstream is not this stage's.
                    let spent = began.elapsed().as_secs_f64();
                    job.add_stage_seconds(name, spent);
                    *totals.lock().expect("totals").entry(name.clone()).or_insert(0.0) += spent;
                    let target = match port {
                        Port::Next => graph.next[i],
                        Port::Done => graph.done[i],
                    }
                    .ok_or_else(|| Error::parameter(format!("stage '{name}'"), format!("emitted on {port:?}, which is not connected")))?;
                    if let Some((_, rx)) = &tokens[target] {
                        if !graph.is_loop_back(i, target) {
                            loop {
                                match rx.recv_timeout(POLL) {
                                    Ok(()) => break,
                                    Err(RecvTimeoutError::Timeout) if !stopped() => continue,
                                    Err(_) => return Err(Error::Interrupted("pipeline stopping".into())),
                                }
                            }
                        }
                    }
                    let mut job = Some(job);
                    loop {
                        match channels[target].0.send_timeout(job.take().expect("job"), POLL) {
                            Ok(()) => break,
                            Err(crossbeam_channel::SendTimeoutError::Timeout(j)) if !stopped() => job = Some(j),
                            Err(_) => return Err(Error::Interrupted("pipeline stopping".into())),
                        }
                    }
                    if port == Port::Done {
                        // Leaving the loop this residual update belongs to.
                        if let Some(step) = graph.next[i] {
                            if let Some((tx, _)) = &tokens[step] {
                                let _ = tx.send(());
                            }
                        }
                    }
                    Ok(())
                };
                let result: Result<()> = match stage {
                    Built::Source(mut source) => {
                        // A job's source time is the time since the previous job left (reading it).
                        let mut since = Instant::now();
                        // Products are named after job ids: a repeated one would overwrite
                        // another job's (a split part named like a file, say).
                        let mut ids = std::collections::HashSet::new();
                        let mut emit = |job: J| {
                            if !ids.insert(job.id().to_string()) {
                                return Err(Error::parameter(
                                    "job id",
                                    format!("'{}' comes twice from this source: the second job's products would overwrite the first's", job.id()),
                                ));
                            }
                            let sent = send(Port::Next, job, since);
                            since = Instant::now();
                            sent
                        };
                        contain_stage_panic(|| source.produce(&mut emit, stopped)).map_err(|e| {
                            let job = source.current_job().unwrap_or_else(|| "-".into());
                            stage_error(name, kind, &job, e)
                        })
                    }
                    Built::Stage(mut stage) => {
                        // The last job this stage had, to name in an error of its finish.
                        let mut last_job = "-".to_string();
                        loop {
                            if stopped() {
                                break Ok(());
                            }
                            let job = match channels[i].1.recv_timeout(POLL) {
                                Ok(job) => job,
                                Err(_) => {
                                    let inputs_done = upstream[i].iter().all(|&u| ended[u].load(Ordering::SeqCst));
                                    let loop_empty = tokens[i].as_ref().is_none_or(|(_, rx)| rx.len() == cap);
                                    if inputs_done && loop_empty && channels[i].1.is_empty() {
                                        // A stage upstream that failed its finish has stopped
                                        // the run before it ended: nothing is settled after it.
                                        if stopped() {
                                            break Ok(());
                                        }
                                        break contain_stage_panic(|| stage.finish()).map_err(|e| stage_error(name, kind, &last_job, e));
                                    }
                                    continue;
                                }
                            };
                            let id = job.id().to_string();
                            last_job.clone_from(&id);
                            progress(&Progress::Working { stage: name.clone(), job: id.clone(), iteration: job.iteration(), of: job.iterations_planned() });
                            let began = Instant::now();
                            // A sink passing its jobs on (the product sink before a writer) ends nothing.
                            let sink = graph.roles[i] == Role::Sink && graph.next[i].is_none();
                            let mut emit = |port: Port, job: J| send(port, job, began);
                            if let Err(e) = contain_stage_panic(|| stage.process(job, &mut emit)) {
                                break Err(stage_error(name, kind, &id, e));
                            }
                            progress(&Progress::Idle { stage: name.clone() });
                            if sink {
                                *totals.lock().expect("totals").entry(name.clone()).or_insert(0.0) += began.elapsed().as_secs_f64();
                                finished.lock().expect("finished list").push(id.clone());
                                progress(&Progress::Finished { job: id });
                            }
                        }
                    }
                };
                if let Err(e) = result {
                    if matches!(e, Error::Stage { ref source, .. } if matches!(**source, Error::Interrupted(_))) {
                        // Stopped because another stage failed: that one reports.
                    } else if graph.roles[i] == Role::Source {
                        // The failed job never entered the pipeline: let the jobs in flight
                        // finish, then report.
                        record(e);
                    } else {
                        fail(e);
                    }
                }
            });
            if let Err(e) = spawned {
                ended[i].store(true, Ordering::SeqCst);
                no_thread(format!("stage '{}'", config.stages[i].name), e);
            }
        }
    });

    if let Some(e) = first_error.into_inner().expect("error slot") {
        return Err(e);
    }
    if stop.is_stopped() {
        return Err(Error::Interrupted(format!(
            "{} job(s) finished before the stop",
            finished.lock().expect("finished").len()
        )));
    }
    Ok(RunReport {
        jobs: finished.into_inner().expect("finished"),
        seconds: start.elapsed().as_secs_f64(),
        stage_seconds: totals.into_inner().expect("totals"),
        written: BTreeMap::new(),
    })
}

/// Runs a stage's work, turning a panic (a bug in the stage) into an error, so that the run
/// ends with the stage and job named instead of losing the thread that other stages wait on.
/// The default panic hook has already printed the panic's location, which a bug report needs.
fn contain_stage_panic(work: impl FnOnce() -> Result<()>) -> Result<()> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(work))
        .unwrap_or_else(|payload| Err(Error::Panic(crate::error::panic_message(payload.as_ref()))))
}

/// Marks a stage ended when its thread leaves, also by a panic outside [`contain_stage_panic`]
/// (which then stops the run: the scope re-raises the panic once every thread has ended).
struct EndedOnExit<'a> {
    ended: &'a AtomicBool,
    stop: &'a RunStop,
}

impl Drop for EndedOnExit<'_> {
    fn drop(&mut self) {
        if std::thread::panicking() {
            self.stop.stop();
        }
        self.ended.store(true, Ordering::SeqCst);
    }
}

fn stage_error(stage: &str, kind: &str, job: &str, e: Error) -> Error {
    Error::Stage { stage: stage.to_string(), kind: kind.to_string(), job: job.to_string(), source: Box::new(e) }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::pipeline::{Emit, KindFn, ProductKind, Source, Stage};
    use std::path::Path;

    /// A payload of the machinery's own: an id and nothing else.
    struct Item(String);

    #[derive(Clone, Copy, Debug, PartialEq, Eq)]
    enum Nothing {}
    impl ProductKind for Nothing {
        fn describe(self) -> (&'static str, &'static str) {
            match self {}
        }
    }

    impl Payload for Item {
        type Product = Nothing;
        type Context = ();
        type SourceInfo = ();
        fn id(&self) -> &str {
            &self.0
        }
        fn iteration(&self) -> usize {
            0
        }
        fn add_stage_seconds(&mut self, _: &str, _: f64) {}
    }

    const PIPELINE: &str = "stages:\n  source: {kind: emit, to: weights}\n  weights: {kind: pass, to: write}\n  write: {kind: sink}\n";

    /// Emits one item named `j1`.
    struct OneJob;
    impl Source<Item> for OneJob {
        fn produce(&mut self, emit: &mut dyn FnMut(Item) -> Result<()>, _: &dyn Fn() -> bool) -> Result<()> {
            emit(Item("j1".into()))
        }
    }

    /// Panics on every item, as a stage with a bug would.
    struct Panics;
    impl Stage<Item> for Panics {
        fn process(&mut self, _: Item, _: &mut Emit<'_, Item>) -> Result<()> {
            panic!("boom")
        }
    }

    /// Passes items on.
    struct Passes;
    impl Stage<Item> for Passes {
        fn process(&mut self, item: Item, emit: &mut Emit<'_, Item>) -> Result<()> {
            emit(Port::Next, item)
        }
    }

    /// Takes items and emits nothing.
    struct Swallows;
    impl Stage<Item> for Swallows {
        fn process(&mut self, _: Item, _: &mut Emit<'_, Item>) -> Result<()> {
            Ok(())
        }
    }

    fn registry() -> Registry<Item> {
        let kind = |name, role, build| KindFn { name, role, consumes: &[], produces: &[], consumes_also: None, passes_on: false, build };
        let mut registry = Registry::new();
        registry.register(kind("emit", Role::Source, |_| Ok(Built::Source(Box::new(OneJob))))).unwrap();
        registry.register(kind("pass", Role::Transform, |_| Ok(Built::Stage(Box::new(Passes))))).unwrap();
        registry.register(kind("sink", Role::Sink, |_| Ok(Built::Stage(Box::new(Swallows))))).unwrap();
        registry
    }

    /// Runs PIPELINE with `source` and the middle stage replaced; `None` if it has not ended
    /// after a minute.
    fn run_with(source: Box<dyn Source<Item>>, weights: Box<dyn Stage<Item>>) -> Option<Result<RunReport>> {
        run_with_sink(source, weights, Box::new(Swallows))
    }

    /// [`run_with`], the sink replaced too.
    fn run_with_sink(source: Box<dyn Source<Item>>, weights: Box<dyn Stage<Item>>, write: Box<dyn Stage<Item>>) -> Option<Result<RunReport>> {
        let config = PipelineSpec::parse(PIPELINE, Path::new("p.yaml"), &[]).unwrap();
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let registry = registry();
            let graph = Graph::build(&registry, &config).unwrap();
            let mut built = build_all(&registry, &config, &graph, &(), false).unwrap();
            built[0] = Built::Source(source);
            built[1] = Built::Stage(weights);
            built[2] = Built::Stage(write);
            let _ = tx.send(run_built(&config, &graph, built, &RunStop::new(), &AtomicBool::new(false), &|_| {}));
        });
        match rx.recv_timeout(Duration::from_secs(60)) {
            Ok(result) => Some(result),
            Err(std::sync::mpsc::RecvTimeoutError::Timeout) => None,
            Err(e) => panic!("the test's pipeline was not built: {e}"),
        }
    }

    #[test]
    fn items_flow_to_the_sink() {
        let report = run_with(Box::new(OneJob), Box::new(Passes)).expect("the run ended").expect("the run succeeded");
        assert_eq!(report.jobs, vec!["j1".to_string()]);
    }

    #[test]
    fn a_panicking_stage_fails_the_run_naming_it_instead_of_hanging() {
        let result = run_with(Box::new(OneJob), Box::new(Panics)).expect("the run hung after a stage panicked");
        let err = result.err().expect("a panicking stage failed the run").to_string();
        for expected in ["stage 'weights' (pass)", "job 'j1'", "boom"] {
            assert!(err.contains(expected), "'{expected}' missing from: {err}");
        }
    }

    /// Panics while producing, before any item.
    struct PanickingSource;
    impl Source<Item> for PanickingSource {
        fn produce(&mut self, _: &mut dyn FnMut(Item) -> Result<()>, _: &dyn Fn() -> bool) -> Result<()> {
            panic!("source boom")
        }
    }

    /// Emits two items with the same id, as a split whose part ids collide with a file's would.
    struct SameIdTwice;
    impl Source<Item> for SameIdTwice {
        fn produce(&mut self, emit: &mut dyn FnMut(Item) -> Result<()>, cancelled: &dyn Fn() -> bool) -> Result<()> {
            OneJob.produce(emit, cancelled)?;
            OneJob.produce(emit, cancelled)
        }
    }

    #[test]
    fn a_job_id_emitted_twice_fails_the_run() {
        let result = run_with(Box::new(SameIdTwice), Box::new(Swallows)).expect("the run ended");
        let err = result.err().expect("a repeated job id failed the run").to_string();
        assert!(err.contains("stage 'source'") && err.contains("'j1'") && err.contains("twice"), "{err}");
    }

    #[test]
    fn a_panicking_source_fails_the_run_naming_it() {
        let result = run_with(Box::new(PanickingSource), Box::new(Panics)).expect("the run hung after the source panicked");
        let err = result.err().expect("a panicking source failed the run").to_string();
        assert!(err.contains("stage 'source' (emit)") && err.contains("source boom"), "{err}");
    }

    /// Passes items on, then fails to finish (a plugin that crashes as it is torn down).
    struct FailsToFinish;
    impl Stage<Item> for FailsToFinish {
        fn process(&mut self, item: Item, emit: &mut Emit<'_, Item>) -> Result<()> {
            emit(Port::Next, item)
        }
        fn finish(&mut self) -> Result<()> {
            Err(Error::parameter("teardown", "crashed"))
        }
    }

    /// Takes items and sets its flag when it finishes (commits what it held).
    struct FinishFlag(Arc<AtomicBool>);
    impl Stage<Item> for FinishFlag {
        fn process(&mut self, _: Item, _: &mut Emit<'_, Item>) -> Result<()> {
            Ok(())
        }
        fn finish(&mut self) -> Result<()> {
            self.0.store(true, Ordering::SeqCst);
            Ok(())
        }
    }

    #[test]
    fn a_stage_that_fails_to_finish_fails_the_run_and_the_stages_after_it_finish_nothing() {
        let finished = Arc::new(AtomicBool::new(false));
        let result = run_with_sink(Box::new(OneJob), Box::new(FailsToFinish), Box::new(FinishFlag(finished.clone()))).expect("the run ended");
        let err = result.err().expect("a failed finish failed the run").to_string();
        assert_eq!(err, "stage 'weights' (pass), job 'j1': invalid teardown: crashed");
        assert!(!finished.load(Ordering::SeqCst), "the sink finished after a stage before it failed to");
        // Finished in order when all goes well.
        let result = run_with_sink(Box::new(OneJob), Box::new(Passes), Box::new(FinishFlag(finished.clone()))).expect("the run ended");
        assert_eq!(result.expect("the run succeeded").jobs, vec!["j1".to_string()]);
        assert!(finished.load(Ordering::SeqCst), "the sink did not finish");
    }
}
