//! The stage graph: checked before any work starts. Every `to`/`done` must name a stage,
//! there is one source, every stage is reachable, and the only cycle allowed is the imaging
//! loop (network step -> residual update -> network step).

use super::config::PipelineSpec;
use super::registry::{Registry, Role};
use super::stage::Payload;
use crate::Result;

/// Edges of the checked graph, by stage index in file order.
#[derive(Clone, Debug)]
pub struct Graph {
    pub roles: Vec<Role>,
    pub next: Vec<Option<usize>>,
    pub done: Vec<Option<usize>>,
    pub source: usize,
}

impl Graph {
    pub fn build<J: Payload>(registry: &Registry<J>, config: &PipelineSpec) -> Result<Graph> {
        let names: Vec<&str> = config.stages.iter().map(|s| s.name.as_str()).collect();
        let mut roles = Vec::new();
        let mut passes_on = Vec::new();
        for s in &config.stages {
            let kind = registry.kind_of(config, s)?;
            roles.push(kind.role());
            passes_on.push(kind.passes_on());
        }
        let resolve = |stage: &str, key: &str, target: &Option<String>| -> Result<Option<usize>> {
            match target {
                None => Ok(None),
                Some(t) => names.iter().position(|n| n == t).map(Some).ok_or_else(|| {
                    config.stage_error(
                        stage,
                        Some(key),
                        &format!("stages.{stage}.{key}: no stage named '{t}' (stages: {})", names.join(", ")),
                    )
                }),
            }
        };
        let mut next = Vec::new();
        let mut done = Vec::new();
        for (i, s) in config.stages.iter().enumerate() {
            next.push(resolve(&s.name, "to", &s.to)?);
            done.push(resolve(&s.name, "done", &s.done)?);
            let err = |key: Option<&str>, msg: String| Err(config.stage_error(&s.name, key, &msg));
            match roles[i] {
                Role::Sink if s.to.is_some() && !passes_on[i] => return err(Some("to"), format!("stages.{}: a {} stage ends the pipeline and takes no `to`", s.name, s.kind)),
                Role::Sink => {}
                _ if s.to.is_none() => return err(None, format!("stages.{}: missing `to` (the stage its jobs go to next)", s.name)),
                _ => {}
            }
            if roles[i] == Role::Residual && s.done.is_none() {
                return err(None, format!("stages.{}: a residual update needs `done` (where jobs go when the loop ends)", s.name));
            }
            if roles[i] != Role::Residual && s.done.is_some() {
                return err(Some("done"), format!("stages.{}: only a residual update has a `done` exit", s.name));
            }
        }
        let sources: Vec<usize> = (0..roles.len()).filter(|&i| roles[i] == Role::Source).collect();
        let source = match sources.as_slice() {
            [one] => *one,
            [] => return Err(crate::Error::input(&config.file, format!("no source stage (kinds: {})", registry.names_with_role(Role::Source).join(", ")))),
            [_, second, ..] => {
                return Err(config.stage_error(&config.stages[*second].name, None, "only one source stage per pipeline"))
            }
        };
        for (i, r) in roles.iter().enumerate() {
            let feeds_source = next[i] == Some(source) || done[i] == Some(source);
            if feeds_source && *r != Role::Source {
                return Err(config.stage_error(&config.stages[i].name, Some("to"), "a source stage cannot receive jobs"));
            }
        }
        let graph = Graph { roles, next, done, source };
        graph.check_cycles(config)?;
        graph.check_reachable(config)?;
        Ok(graph)
    }

    /// Is the edge `from -> to` the back edge of an imaging loop (residual -> step whose `to`
    /// is that residual)?
    pub fn is_loop_back(&self, from: usize, to: usize) -> bool {
        self.roles[from] == Role::Residual && self.roles[to] == Role::Step && self.next[to] == Some(from)
    }

    fn check_cycles(&self, config: &PipelineSpec) -> Result<()> {
        // Depth-first search over the graph without loop back edges: any cycle left is wrong.
        let n = self.roles.len();
        let mut state = vec![0u8; n]; // 0 new, 1 on stack, 2 done
        fn visit(g: &Graph, i: usize, state: &mut [u8], stack: &mut Vec<usize>) -> Option<Vec<usize>> {
            state[i] = 1;
            stack.push(i);
            for j in [g.next[i], g.done[i]].into_iter().flatten() {
                if g.is_loop_back(i, j) {
                    continue;
                }
                if state[j] == 1 {
                    let start = stack.iter().position(|&s| s == j).unwrap_or(0);
                    return Some(stack[start..].to_vec());
                }
                if state[j] == 0 {
                    if let Some(c) = visit(g, j, state, stack) {
                        return Some(c);
                    }
                }
            }
            stack.pop();
            state[i] = 2;
            None
        }
        for i in 0..n {
            if state[i] == 0 {
                if let Some(cycle) = visit(self, i, &mut state, &mut Vec::new()) {
                    let names: Vec<&str> = cycle.iter().map(|&k| config.stages[k].name.as_str()).collect();
                    return Err(config.stage_error(
                        names[0],
                        Some("to"),
                        &format!(
                            "cycle {} -> {}: the only loop allowed is a network step and a residual update pointing at each other",
                            names.join(" -> "),
                            names[0]
                        ),
                    ));
                }
            }
        }
        Ok(())
    }

    /// `reach[i][j]`: a job leaving stage `i` can come to stage `j` (loop edges included).
    pub fn reach(&self) -> Vec<Vec<bool>> {
        let n = self.roles.len();
        (0..n)
            .map(|i| {
                let mut seen = vec![false; n];
                let mut stack: Vec<usize> = [self.next[i], self.done[i]].into_iter().flatten().collect();
                while let Some(j) = stack.pop() {
                    if !std::mem::replace(&mut seen[j], true) {
                        stack.extend([self.next[j], self.done[j]].into_iter().flatten());
                    }
                }
                seen
            })
            .collect()
    }

    fn check_reachable(&self, config: &PipelineSpec) -> Result<()> {
        let mut seen = vec![false; self.roles.len()];
        let mut stack = vec![self.source];
        while let Some(i) = stack.pop() {
            if std::mem::replace(&mut seen[i], true) {
                continue;
            }
            stack.extend([self.next[i], self.done[i]].into_iter().flatten());
        }
        if let Some(i) = seen.iter().position(|s| !s) {
            return Err(config.stage_error(&config.stages[i].name, None, &format!("stage '{}' is never reached from the source", config.stages[i].name)));
        }
        if !self.roles.iter().zip(&seen).any(|(r, s)| *r == Role::Sink && *s) {
            return Err(crate::Error::input(&config.file, "no writer stage: the pipeline would produce nothing"));
        }
        Ok(())
    }
}
