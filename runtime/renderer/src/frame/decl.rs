//! What each pass reads and writes, and the check that a frame's passes run in an order that
//! makes every read see a write.
//!
//! Each pass module declares its pass as a [`PassDecl`] (`pub const PASS`), with resource
//! names such as `SceneDepth`, `GBufferA`, `SceneColor`; a pass's named steps that belong to
//! other modules (the particles' `ParticleCollision` in the BasePass) declare their own. A
//! frame lists its passes, in frame order, as a [`FramePlan`] built from those declarations
//! (its unit tests check the plan); the frame records each pass under its declaration's name.

/// One pass (or a step recorded inside another module's pass) and the resources it touches.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PassDecl {
    pub name: &'static str,
    pub reads: &'static [&'static str],
    pub writes: &'static [&'static str],
}

/// A frame's passes in frame order, each with the steps other modules record inside it.
#[derive(Clone, Debug, Default)]
pub struct FramePlan {
    /// Resources made before the frame (the scene's buffers, the camera).
    pub inputs: Vec<&'static str>,
    /// Resources read as the previous frame left them before this frame writes them again
    /// (TAA's history): each must be written by some pass of the frame.
    pub history: Vec<&'static str>,
    /// Each pass: its declaration and the parts it records in order (its own declaration
    /// among them).
    pub passes: Vec<(&'static PassDecl, Vec<&'static PassDecl>)>,
}

impl FramePlan {
    pub fn new(inputs: &[&'static str], history: &[&'static str]) -> FramePlan {
        FramePlan { inputs: inputs.to_vec(), history: history.to_vec(), passes: Vec::new() }
    }

    /// Adds a pass.
    pub fn pass(mut self, pass: &'static PassDecl) -> FramePlan {
        self.passes.push((pass, vec![pass]));
        self
    }

    /// Adds a step another module records inside the last pass, after what is there.
    pub fn step(mut self, step: &'static PassDecl) -> FramePlan {
        if let Some((_, parts)) = self.passes.last_mut() {
            parts.push(step);
        }
        self
    }

    /// Adds a step another module records inside the last pass, before the pass's own work
    /// (after the steps added before it this way).
    pub fn step_first(mut self, step: &'static PassDecl) -> FramePlan {
        if let Some((pass, parts)) = self.passes.last_mut() {
            let own = parts.iter().position(|p| std::ptr::eq(*p, *pass)).unwrap_or(parts.len());
            parts.insert(own, step);
        }
        self
    }

    /// The pass names, in frame order (the names `passes.json` lists).
    pub fn names(&self) -> Vec<&'static str> {
        self.passes.iter().map(|(p, _)| p.name).collect()
    }

    /// Every declaration, passes and steps, in the order they record.
    pub fn decls(&self) -> impl Iterator<Item = &'static PassDecl> + '_ {
        self.passes.iter().flat_map(|(_, parts)| parts.iter().copied())
    }

    /// Checks that every resource read is a frame input, a history resource some pass writes,
    /// or written by an earlier pass (or earlier in the same pass: its own earlier step);
    /// returns every violation.
    pub fn check(&self) -> Result<(), Vec<String>> {
        let mut errors = Vec::new();
        let written_anywhere: Vec<&str> = self.decls().flat_map(|d| d.writes.iter().copied()).collect();
        for h in &self.history {
            if !written_anywhere.contains(h) {
                errors.push(format!("history resource {h} is never written by the frame"));
            }
        }
        let mut written: Vec<&str> = Vec::new();
        for d in self.decls() {
            for r in d.reads {
                if !(self.inputs.contains(r) || self.history.contains(r) || written.contains(r)) {
                    errors.push(format!("{} reads {r}, which no earlier pass writes", d.name));
                }
            }
            written.extend(d.writes.iter().copied());
        }
        if errors.is_empty() {
            Ok(())
        } else {
            Err(errors)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const A: PassDecl = PassDecl { name: "A", reads: &["Scene"], writes: &["Depth"] };
    const B: PassDecl = PassDecl { name: "B", reads: &["Depth", "History"], writes: &["Color", "History"] };
    const C: PassDecl = PassDecl { name: "C", reads: &["Color"], writes: &["Output"] };

    #[test]
    fn an_ordered_frame_passes() {
        let plan = FramePlan::new(&["Scene"], &["History"]).pass(&A).pass(&B).step(&C);
        assert_eq!(plan.check(), Ok(()));
        assert_eq!(plan.names(), vec!["A", "B"]);
        let order: Vec<&str> = plan.decls().map(|d| d.name).collect();
        assert_eq!(order, vec!["A", "B", "C"]);
    }

    #[test]
    fn a_read_before_its_write_is_reported() {
        let plan = FramePlan::new(&["Scene"], &["History"]).pass(&B).pass(&A);
        assert_eq!(plan.check(), Err(vec!["B reads Depth, which no earlier pass writes".to_string()]));
    }

    #[test]
    fn a_step_before_the_pass_records_first() {
        // C reads Color, which B writes: as B's first step it runs before B's own work
        let plan = FramePlan::new(&["Scene"], &["History"]).pass(&A).pass(&B).step_first(&C);
        assert_eq!(plan.check(), Err(vec!["C reads Color, which no earlier pass writes".to_string()]));
        assert_eq!(plan.names(), vec!["A", "B"]);
    }

    #[test]
    fn history_nobody_writes_is_reported() {
        let plan = FramePlan::new(&["Scene"], &["Exposure"]).pass(&A);
        assert_eq!(plan.check(), Err(vec!["history resource Exposure is never written by the frame".to_string()]));
    }
}
