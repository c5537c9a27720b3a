//! A light structural reading of SPIR-V, for the modules that go to the device unchanged
//! (SPIR-V passthrough), and the rewrite of their binding numbers to the ones wgpu's Vulkan
//! backend gives the descriptor set layout.
//!
//! Takes the bytes of an artifact; gives its words with every instruction walked once
//! (header, word counts, ids below the bound, the entry point, the resource variables with
//! their set, binding and descriptor class). Guarantees: bytes that are not a whole module,
//! an instruction running past the end, an id at or past the bound, or a resource that the
//! permutation's reflection does not list are errors naming the word, never a module handed
//! to the driver. It is no validator (spirv-val does not exist at run time): modules from
//! archives the runtime does not trust go through naga's SPIR-V front end instead.
//!
//! Why the rewrite: wgpu-hal's Vulkan backend numbers the bindings of a descriptor set layout
//! densely, in the order of the WebGPU binding numbers (a group with bindings 0, 1 and 5 is
//! Vulkan bindings 0, 1 and 2), and rewrites the SPIR-V it generates from WGSL to match.
//! SPIR-V passthrough gets no such rewrite, so a precompiled module whose bindings have gaps
//! names descriptors the layout does not hold (validation: `VUID-VkGraphicsPipelineCreateInfo-
//! layout-00756`) and the driver reads the wrong ones. [`SpirvModule::remap_bindings`] applies the same
//! numbering to the module, from the pipeline layout it is created for.

use std::collections::{HashMap, HashSet};

use kiln_archive::Stage;
use kiln_archive::{BindingKind, Reflection};

const MAGIC: u32 = 0x0723_0203;
/// The highest SPIR-V version the runtime passes through (1.6).
const MAX_VERSION: u32 = 0x0001_0600;
/// Ids a module may declare; naga's modules of the bundled set stay far below.
const MAX_BOUND: u32 = 1 << 22;

const OP_ENTRY_POINT: u32 = 15;
const OP_TYPE_IMAGE: u32 = 25;
const OP_TYPE_SAMPLER: u32 = 26;
const OP_TYPE_ARRAY: u32 = 28;
const OP_TYPE_RUNTIME_ARRAY: u32 = 29;
const OP_TYPE_STRUCT: u32 = 30;
const OP_TYPE_POINTER: u32 = 32;
const OP_VARIABLE: u32 = 59;
const OP_DECORATE: u32 = 71;

const DECORATION_BLOCK: u32 = 2;
const DECORATION_BUFFER_BLOCK: u32 = 3;
const DECORATION_BINDING: u32 = 33;
const DECORATION_DESCRIPTOR_SET: u32 = 34;

const STORAGE_UNIFORM_CONSTANT: u32 = 0;
const STORAGE_UNIFORM: u32 = 2;
const STORAGE_STORAGE_BUFFER: u32 = 12;

/// What a SPIR-V module does wrong, with the word where it was found.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum SpirvError {
    /// The artifact's length is not a whole number of words, or too short for a header.
    #[error("SPIR-V artifact is {0} bytes, not a whole module")]
    Length(usize),
    /// The first word is not SPIR-V's magic number.
    #[error("SPIR-V artifact starts with {0:#010x}, not the SPIR-V magic number")]
    Magic(u32),
    /// The version word is not SPIR-V 1.0 to 1.6.
    #[error("SPIR-V version word {0:#010x} is not a version from 1.0 to 1.6")]
    Version(u32),
    /// The id bound is out of range.
    #[error("SPIR-V id bound {0} is outside 1..={MAX_BOUND}")]
    Bound(u32),
    /// The schema word is not 0.
    #[error("SPIR-V schema word is {0}, not 0")]
    Schema(u32),
    /// An instruction's word count is zero or runs past the end.
    #[error("SPIR-V instruction at word {word} has word count {count}, which {why}")]
    WordCount {
        /// The instruction's first word.
        word: usize,
        /// Its word count.
        count: usize,
        /// What is wrong with it.
        why: &'static str,
    },
    /// An instruction names an id at or past the bound.
    #[error("SPIR-V instruction at word {word} (opcode {opcode}) names id {id}, at or past the bound {bound}")]
    IdOutOfBound {
        /// The instruction's first word.
        word: usize,
        /// Its opcode.
        opcode: u32,
        /// The id it names.
        id: u32,
        /// The module's id bound.
        bound: u32,
    },
    /// An instruction is too short for its operands.
    #[error("SPIR-V instruction at word {word} (opcode {opcode}) is too short for its operands")]
    Operands {
        /// The instruction's first word.
        word: usize,
        /// Its opcode.
        opcode: u32,
    },
    /// No entry point of the permutation's name and stage.
    #[error("SPIR-V module has no {stage} entry point named `{entry}`")]
    NoEntryPoint {
        /// The entry point's name.
        entry: String,
        /// Its stage.
        stage: Stage,
    },
    /// A resource's descriptor class differs from the reflection's.
    #[error(
        "SPIR-V module declares @group({group}) @binding({binding}) as a {found}, \
         but the permutation's reflection {expected}"
    )]
    Resource {
        /// Its descriptor set.
        group: u32,
        /// Its binding.
        binding: u32,
        /// The class the module declares.
        found: &'static str,
        /// What the reflection declares there.
        expected: String,
    },
    /// A resource variable with a set but no binding, or a binding but no set.
    #[error("SPIR-V module gives resource variable %{id} a descriptor set but no binding, or a binding but no set")]
    HalfDecorated {
        /// The variable's id.
        id: u32,
    },
}

/// A resource variable of a module: its set and binding, its class, and where its binding
/// number sits in the words.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Resource {
    /// Its descriptor set (`@group`).
    pub group: u32,
    /// Its binding number.
    pub binding: u32,
    /// Its descriptor class.
    pub class: DescriptorClass,
    binding_word: usize,
}

/// The descriptor class of a resource variable, as the layout must declare it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DescriptorClass {
    /// A uniform buffer.
    UniformBuffer,
    /// A storage buffer.
    StorageBuffer,
    /// A sampler.
    Sampler,
    /// A sampled image (texture).
    SampledImage,
    /// A storage image (storage texture).
    StorageImage,
    /// A type the runtime does not bind (combined image samplers, acceleration structures).
    Other,
}

impl DescriptorClass {
    fn name(self) -> &'static str {
        match self {
            DescriptorClass::UniformBuffer => "uniform buffer",
            DescriptorClass::StorageBuffer => "storage buffer",
            DescriptorClass::Sampler => "sampler",
            DescriptorClass::SampledImage => "sampled texture",
            DescriptorClass::StorageImage => "storage texture",
            DescriptorClass::Other => "resource of another type",
        }
    }

    fn of(kind: &BindingKind) -> DescriptorClass {
        match kind {
            BindingKind::UniformBuffer { .. } => DescriptorClass::UniformBuffer,
            BindingKind::StorageBuffer { .. } => DescriptorClass::StorageBuffer,
            BindingKind::Sampler { .. } => DescriptorClass::Sampler,
            BindingKind::Texture { .. } => DescriptorClass::SampledImage,
            BindingKind::StorageTexture { .. } => DescriptorClass::StorageImage,
        }
    }
}

/// A SPIR-V module walked once: its words and what the runtime needs of them.
#[derive(Clone, Debug)]
pub struct SpirvModule {
    /// The module, one word per element.
    pub words: Vec<u32>,
    /// `(execution model, name)` of every entry point.
    pub entry_points: Vec<(u32, String)>,
    /// Resource variables, in the order they are declared.
    pub resources: Vec<Resource>,
}

/// The words of a SPIR-V artifact, checking the length and the magic number only.
pub fn words(bytes: &[u8]) -> Result<Vec<u32>, SpirvError> {
    if !bytes.len().is_multiple_of(4) || bytes.len() < 20 {
        return Err(SpirvError::Length(bytes.len()));
    }
    let words: Vec<u32> = bytes.chunks_exact(4).map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect();
    if words[0] != MAGIC {
        return Err(SpirvError::Magic(words[0]));
    }
    Ok(words)
}

fn execution_model(stage: Stage) -> u32 {
    match stage {
        Stage::Vertex => 0,
        Stage::Fragment => 4,
        Stage::Compute => 5,
    }
}

/// A nul-terminated literal string starting at `operands[0]`, and how many words it takes.
fn literal_string(operands: &[u32]) -> Option<(String, usize)> {
    let mut bytes = Vec::new();
    for (i, w) in operands.iter().enumerate() {
        for b in w.to_le_bytes() {
            if b == 0 {
                return Some((String::from_utf8_lossy(&bytes).into_owned(), i + 1));
            }
            bytes.push(b);
        }
    }
    None
}

/// The header's version, id bound and schema checked; gives the id bound.
fn header_bound(words: &[u32]) -> Result<u32, SpirvError> {
    let version = words[1];
    if !(0x0001_0000..=MAX_VERSION).contains(&version) || version & 0xff00_00ff != 0 {
        return Err(SpirvError::Version(version));
    }
    let bound = words[3];
    if bound == 0 || bound > MAX_BOUND {
        return Err(SpirvError::Bound(bound));
    }
    if words[4] != 0 {
        return Err(SpirvError::Schema(words[4]));
    }
    Ok(bound)
}

/// One instruction of the walk: the word it starts at, its opcode and operands, and the
/// module's id bound its ids must stay below.
struct Instruction<'a> {
    at: usize,
    opcode: u32,
    ops: &'a [u32],
    bound: u32,
}

impl Instruction<'_> {
    /// At least `n` operands, or an error naming the instruction.
    fn need(&self, n: usize) -> Result<(), SpirvError> {
        if self.ops.len() < n {
            Err(SpirvError::Operands { word: self.at, opcode: self.opcode })
        } else {
            Ok(())
        }
    }

    /// Operand `i` as an id: non-zero and below the bound.
    fn id(&self, i: usize) -> Result<u32, SpirvError> {
        let v = self.ops[i];
        if v == 0 || v >= self.bound {
            Err(SpirvError::IdOutOfBound { word: self.at, opcode: self.opcode, id: v, bound: self.bound })
        } else {
            Ok(v)
        }
    }
}

/// What the walk gathers, per id: entry points, decorations, the types resources can have,
/// and the variables in the resource storage classes.
#[derive(Default)]
struct Declarations {
    entry_points: Vec<(u32, String)>,
    /// Variable -> descriptor set.
    sets: HashMap<u32, u32>,
    /// Variable -> (word of the binding literal, binding).
    bindings: HashMap<u32, (usize, u32)>,
    /// Structs decorated `BufferBlock` (storage buffers of SPIR-V 1.0-1.2).
    buffer_blocks: HashSet<u32>,
    types: HashMap<u32, DescriptorClass>,
    /// Array -> element type.
    element: HashMap<u32, u32>,
    /// Pointer -> (storage class, pointee).
    pointers: HashMap<u32, (u32, u32)>,
    /// (variable, pointer type).
    variables: Vec<(u32, u32)>,
}

impl Declarations {
    /// Records what `ins` declares, checking the operands it reads.
    fn record(&mut self, ins: &Instruction<'_>) -> Result<(), SpirvError> {
        let ops = ins.ops;
        match ins.opcode {
            OP_ENTRY_POINT => {
                ins.need(3)?;
                ins.id(1)?;
                let (name, _) =
                    literal_string(&ops[2..]).ok_or(SpirvError::Operands { word: ins.at, opcode: ins.opcode })?;
                self.entry_points.push((ops[0], name));
            }
            OP_DECORATE => self.record_decoration(ins)?,
            OP_TYPE_SAMPLER => {
                ins.need(1)?;
                self.types.insert(ins.id(0)?, DescriptorClass::Sampler);
            }
            OP_TYPE_IMAGE => {
                ins.need(8)?;
                let class = match ops[6] {
                    2 => DescriptorClass::StorageImage,
                    _ => DescriptorClass::SampledImage,
                };
                self.types.insert(ins.id(0)?, class);
            }
            OP_TYPE_ARRAY | OP_TYPE_RUNTIME_ARRAY => {
                ins.need(2)?;
                self.element.insert(ins.id(0)?, ins.id(1)?);
            }
            OP_TYPE_STRUCT => {
                ins.need(1)?;
                ins.id(0)?;
            }
            OP_TYPE_POINTER => {
                ins.need(3)?;
                self.pointers.insert(ins.id(0)?, (ops[1], ins.id(2)?));
            }
            OP_VARIABLE => {
                ins.need(3)?;
                let ty = ins.id(0)?;
                let var = ins.id(1)?;
                if matches!(ops[2], STORAGE_UNIFORM_CONSTANT | STORAGE_UNIFORM | STORAGE_STORAGE_BUFFER) {
                    self.variables.push((var, ty));
                }
            }
            _ => {}
        }
        Ok(())
    }

    /// `OpDecorate`: the descriptor set, the binding (and the word of its literal, which
    /// the remap rewrites) and `BufferBlock`; other decorations are not the runtime's.
    fn record_decoration(&mut self, ins: &Instruction<'_>) -> Result<(), SpirvError> {
        ins.need(2)?;
        let target = ins.id(0)?;
        match ins.ops[1] {
            DECORATION_DESCRIPTOR_SET => {
                ins.need(3)?;
                self.sets.insert(target, ins.ops[2]);
            }
            DECORATION_BINDING => {
                ins.need(3)?;
                self.bindings.insert(target, (ins.at + 3, ins.ops[2]));
            }
            DECORATION_BUFFER_BLOCK => {
                self.buffer_blocks.insert(target);
            }
            DECORATION_BLOCK => {}
            _ => {}
        }
        Ok(())
    }

    /// The resource variables (those with a set and a binding), in declaration order.
    fn resources(&self) -> Result<Vec<Resource>, SpirvError> {
        let mut resources = Vec::new();
        for &(var, ty) in &self.variables {
            let (set, binding) = (self.sets.get(&var), self.bindings.get(&var));
            let (Some(&group), Some(&(binding_word, binding))) = (set, binding) else {
                if set.is_some() || binding.is_some() {
                    return Err(SpirvError::HalfDecorated { id: var });
                }
                continue;
            };
            let Some(&(storage, pointee)) = self.pointers.get(&ty) else {
                return Err(SpirvError::Resource {
                    group,
                    binding,
                    found: "variable whose type is not a pointer",
                    expected: "lists no such thing".into(),
                });
            };
            let class = self.class(storage, pointee);
            resources.push(Resource { group, binding, class, binding_word });
        }
        Ok(resources)
    }

    /// The descriptor class of a variable in `storage` pointing at `pointee`.
    fn class(&self, storage: u32, mut pointee: u32) -> DescriptorClass {
        // Arrays of resources bind as one descriptor of their element's class.
        let mut depth = 0;
        while let Some(&e) = self.element.get(&pointee) {
            pointee = e;
            depth += 1;
            if depth > 8 {
                break;
            }
        }
        match storage {
            STORAGE_STORAGE_BUFFER => DescriptorClass::StorageBuffer,
            STORAGE_UNIFORM if self.buffer_blocks.contains(&pointee) => DescriptorClass::StorageBuffer,
            STORAGE_UNIFORM => DescriptorClass::UniformBuffer,
            _ => self.types.get(&pointee).copied().unwrap_or(DescriptorClass::Other),
        }
    }
}

impl SpirvModule {
    /// Walks every instruction of `bytes` once.
    pub fn parse(bytes: &[u8]) -> Result<SpirvModule, SpirvError> {
        let words = words(bytes)?;
        let bound = header_bound(&words)?;
        let mut declarations = Declarations::default();
        let mut at = 5;
        while at < words.len() {
            let count = (words[at] >> 16) as usize;
            let opcode = words[at] & 0xffff;
            if count == 0 {
                return Err(SpirvError::WordCount { word: at, count, why: "is zero" });
            }
            if at + count > words.len() {
                return Err(SpirvError::WordCount { word: at, count, why: "runs past the end of the module" });
            }
            declarations.record(&Instruction { at, opcode, ops: &words[at + 1..at + count], bound })?;
            at += count;
        }
        let resources = declarations.resources()?;
        Ok(SpirvModule { words, entry_points: declarations.entry_points, resources })
    }

    /// Checks the module against the reflection of the permutation it serves: an entry
    /// point of that name and stage, and every resource variable at a (group, binding) the
    /// reflection lists, of the same descriptor class.
    pub fn check(&self, reflection: &Reflection) -> Result<(), SpirvError> {
        let model = execution_model(reflection.stage);
        if !self.entry_points.iter().any(|(m, n)| *m == model && *n == reflection.entry) {
            return Err(SpirvError::NoEntryPoint { entry: reflection.entry.clone(), stage: reflection.stage });
        }
        for r in &self.resources {
            let listed = reflection.bindings.iter().find(|b| b.group == r.group && b.binding == r.binding);
            let expected = match listed {
                None => "lists nothing there".to_string(),
                Some(b) if DescriptorClass::of(&b.kind) == r.class => continue,
                Some(b) => format!("says it is a {}", DescriptorClass::of(&b.kind).name()),
            };
            return Err(SpirvError::Resource { group: r.group, binding: r.binding, found: r.class.name(), expected });
        }
        Ok(())
    }

    /// The module's words with every resource's binding number replaced by
    /// `vulkan_binding(group, binding)`; `None` when nothing changes.
    pub fn remap_bindings(&self, vulkan_binding: impl Fn(u32, u32) -> u32) -> Option<Vec<u32>> {
        let mut out: Option<Vec<u32>> = None;
        for r in &self.resources {
            let to = vulkan_binding(r.group, r.binding);
            if to != r.binding {
                out.get_or_insert_with(|| self.words.clone())[r.binding_word] = to;
            }
        }
        out
    }
}

/// The Vulkan binding numbers wgpu-hal gives a pipeline layout: within each group, the
/// bindings numbered densely in ascending order of their WebGPU binding numbers.
#[derive(Clone, Debug, Default, PartialEq, Eq, Hash)]
pub struct VulkanBindings {
    /// Per group, the WebGPU binding numbers in ascending order.
    groups: Vec<Vec<u32>>,
}

impl VulkanBindings {
    /// The numbering of `groups`: per group, the WebGPU binding numbers it holds.
    pub fn new(groups: Vec<Vec<u32>>) -> VulkanBindings {
        let mut groups = groups;
        for g in &mut groups {
            g.sort_unstable();
        }
        VulkanBindings { groups }
    }

    /// The Vulkan binding of `binding` in `group` (itself where the layout lacks it: the
    /// check against the reflection has already refused such a module).
    pub fn get(&self, group: u32, binding: u32) -> u32 {
        self.groups
            .get(group as usize)
            .and_then(|g| g.binary_search(&binding).ok())
            .map(|i| i as u32)
            .unwrap_or(binding)
    }
}

#[cfg(test)]
mod tests {
    use kiln_archive::{Binding, SampleKind, TextureDim};

    use super::*;

    /// A fragment module `main` with a uniform buffer at (0, 5) and a sampler at (1, 2).
    fn module() -> Vec<u32> {
        let mut w = vec![MAGIC, 0x0001_0000, 0, 20, 0];
        let mut op = |opcode: u32, ops: &[u32]| {
            w.push(((ops.len() as u32 + 1) << 16) | opcode);
            w.extend_from_slice(ops);
        };
        // "main\0" in one word plus a nul word.
        op(OP_ENTRY_POINT, &[4, 1, u32::from_le_bytes(*b"main"), 0]);
        op(OP_DECORATE, &[10, DECORATION_DESCRIPTOR_SET, 0]);
        op(OP_DECORATE, &[10, DECORATION_BINDING, 5]);
        op(OP_DECORATE, &[11, DECORATION_DESCRIPTOR_SET, 1]);
        op(OP_DECORATE, &[11, DECORATION_BINDING, 2]);
        op(OP_DECORATE, &[3, DECORATION_BLOCK]);
        op(OP_TYPE_STRUCT, &[3, 2]);
        op(OP_TYPE_POINTER, &[4, STORAGE_UNIFORM, 3]);
        op(OP_TYPE_SAMPLER, &[5]);
        op(OP_TYPE_POINTER, &[6, STORAGE_UNIFORM_CONSTANT, 5]);
        op(OP_VARIABLE, &[4, 10, STORAGE_UNIFORM]);
        op(OP_VARIABLE, &[6, 11, STORAGE_UNIFORM_CONSTANT]);
        w
    }

    fn bytes(words: &[u32]) -> Vec<u8> {
        words.iter().flat_map(|w| w.to_le_bytes()).collect()
    }

    fn reflection(bindings: Vec<Binding>) -> Reflection {
        Reflection {
            entry: "main".into(),
            stage: Stage::Fragment,
            bindings,
            vertex_inputs: vec![],
            color_outputs: vec![],
            workgroup_size: None,
        }
    }

    fn listed() -> Vec<Binding> {
        vec![
            Binding { group: 0, binding: 5, name: None, kind: BindingKind::UniformBuffer { min_size: 16 } },
            Binding { group: 1, binding: 2, name: None, kind: BindingKind::Sampler { comparison: false } },
        ]
    }

    #[test]
    fn resources_are_found_with_their_class() {
        let m = SpirvModule::parse(&bytes(&module())).unwrap();
        let found: Vec<(u32, u32, DescriptorClass)> =
            m.resources.iter().map(|r| (r.group, r.binding, r.class)).collect();
        assert_eq!(found, [(0, 5, DescriptorClass::UniformBuffer), (1, 2, DescriptorClass::Sampler)]);
        m.check(&reflection(listed())).unwrap();
    }

    #[test]
    fn bindings_are_renumbered_as_wgpu_hal_numbers_the_layout() {
        let m = SpirvModule::parse(&bytes(&module())).unwrap();
        // Group 0 holds bindings 0 and 5 (Vulkan 0 and 1); group 1 holds 2 and 7 (0 and 1).
        let map = VulkanBindings::new(vec![vec![5, 0], vec![7, 2]]);
        let words = m.remap_bindings(|g, b| map.get(g, b)).unwrap();
        let again = SpirvModule::parse(&bytes(&words)).unwrap();
        let found: Vec<(u32, u32)> = again.resources.iter().map(|r| (r.group, r.binding)).collect();
        assert_eq!(found, [(0, 1), (1, 0)]);
        // A dense layout changes nothing.
        let dense = VulkanBindings::new(vec![vec![0, 1, 2, 3, 4, 5], vec![0, 1, 2]]);
        assert_eq!(m.remap_bindings(|g, b| dense.get(g, b)), None);
    }

    #[test]
    fn a_resource_the_reflection_does_not_list_or_types_otherwise_is_refused() {
        let m = SpirvModule::parse(&bytes(&module())).unwrap();
        let e = m.check(&reflection(listed()[..1].to_vec())).unwrap_err();
        assert_eq!(
            e.to_string(),
            "SPIR-V module declares @group(1) @binding(2) as a sampler, but the permutation's reflection lists nothing there"
        );
        let mut other = listed();
        other[1].kind = BindingKind::Texture { dim: TextureDim::D2, sample: SampleKind::Float, multisampled: false };
        let e = m.check(&reflection(other)).unwrap_err();
        assert_eq!(
            e.to_string(),
            "SPIR-V module declares @group(1) @binding(2) as a sampler, but the permutation's reflection says it is a sampled texture"
        );
        let mut vertex = reflection(listed());
        vertex.stage = Stage::Vertex;
        assert_eq!(m.check(&vertex).unwrap_err().to_string(), "SPIR-V module has no vertex entry point named `main`");
    }

    #[test]
    fn structural_damage_is_an_error_naming_the_word() {
        let good = module();
        let e = |w: &[u32]| SpirvModule::parse(&bytes(w)).unwrap_err().to_string();
        assert_eq!(e(&good[..4]), "SPIR-V artifact is 16 bytes, not a whole module");
        let mut bad = good.clone();
        bad[0] ^= 1;
        assert_eq!(e(&bad), "SPIR-V artifact starts with 0x07230202, not the SPIR-V magic number");
        let mut bad = good.clone();
        bad[1] = 0x0002_0000;
        assert_eq!(e(&bad), "SPIR-V version word 0x00020000 is not a version from 1.0 to 1.6");
        let mut bad = good.clone();
        bad[3] = 0;
        assert_eq!(e(&bad), "SPIR-V id bound 0 is outside 1..=4194304");
        let mut bad = good.clone();
        bad[5] &= 0xffff; // word count 0
        assert_eq!(e(&bad), "SPIR-V instruction at word 5 has word count 0, which is zero");
        let mut bad = good.clone();
        bad[5] += 0x0100_0000; // word count 5 + 256
        assert_eq!(e(&bad), "SPIR-V instruction at word 5 has word count 261, which runs past the end of the module");
        let mut bad = good.clone();
        bad[11] = 99; // the target of the first decoration
        assert_eq!(e(&bad), "SPIR-V instruction at word 10 (opcode 71) names id 99, at or past the bound 20");
        // A lone binding without its set.
        let mut bad = good;
        bad[12] = 0; // DescriptorSet of %10 becomes decoration 0 (RelaxedPrecision)
        assert_eq!(
            e(&bad),
            "SPIR-V module gives resource variable %10 a descriptor set but no binding, or a binding but no set"
        );
    }

    #[test]
    fn every_flipped_bit_of_a_module_is_an_error_or_keeps_it_checked() {
        // No bit flip panics or hides a resource from the check.
        let good = module();
        let r = reflection(listed());
        for word in 0..good.len() {
            for bit in 0..32 {
                let mut w = good.clone();
                w[word] ^= 1 << bit;
                if let Ok(m) = SpirvModule::parse(&bytes(&w)) {
                    let _ = m.check(&r);
                }
            }
        }
    }
}
