//! The kernel's SPIR-V, written here by naga rather than inside wgpu, for two reasons, each an edit of the SPIR-V
//! before it goes to the driver (`wgpu::Features::PASSTHROUGH_SHADERS`):
//! - WGSL zero-initializes every variable, and the driver carries that out at the start of every invocation — for
//!   the traversal stack, 1 KiB of stores a ray. The arrays in [`WRITTEN_BEFORE_READ`] never need it, so their
//!   initializers are dropped. On an H100 this made the flat scene's kernel 21–24% faster (BENCHMARKS.md, "wgpu
//!   kernel step 3").
//! - WGSL leaves `min` and `max` of a NaN undefined, so the kernel had to test for NaN itself where the CPU's box
//!   test relies on Rust's rule (a NaN operand is ignored); [`ignore_nan_operands`] gives every float `min`, `max`
//!   and `clamp` that rule instead.
//!
//! - SPIR-V lets a driver fuse a multiply and an add into one FMA (NVIDIA's does) unless the result is decorated
//!   `NoContraction`; naga never writes that decoration. Fused, the watertight test's edge functions of two
//!   triangles sharing an edge are no longer exact negations of each other, so a ray through the edge could hit
//!   both or neither, and the kernel's answers round otherwise than the CPU's (Rust never fuses on its own).
//!   [`forbid_contraction`] decorates every float multiply, add and subtract of the triangle test
//!   ([`EXACT_FUNCTIONS`]); the kernel's own `fma` calls, where the CPU calls `mul_add`, stay fused. Elsewhere (the
//!   box tests, the rays' transforms) a fused operation only rounds otherwise, and forbidding it everywhere cost the
//!   kernels 1–5% on an H100 (BENCHMARKS.md, "No contraction in the GPU's triangle test").
//!
//! The rest is what wgpu would do itself on Vulkan: pipeline constants applied by naga, the module written for the
//! one entry point, workgroup memory zeroed by naga's polyfill; without naga's run-time checks (see
//! [`super::kernel::Kernel::new`]).

use naga::back::spv;

/// The `var<private>` arrays of `trace.wgsl` that the kernel always writes before it reads them: the traversal
/// stack (an entry is read only once pushed) and the per-level ray and object (level 0 is set when a ray's walk
/// begins, level `l + 1` when it descends from `l`, and only levels up to the current one are read).
const WRITTEN_BEFORE_READ: [&str; 4] = ["stack", "level_object", "level_origin", "level_direction"];

/// SPIR-V's `OpName`, `OpExtInstImport`, `OpExtInst`, `OpVariable`, `OpDecorate` and `OpMemberDecorate` opcodes.
const OP_NAME: u32 = 5;
const OP_EXT_INST_IMPORT: u32 = 11;
const OP_EXT_INST: u32 = 12;
const OP_VARIABLE: u32 = 59;
const OP_DECORATE: u32 = 71;
const OP_MEMBER_DECORATE: u32 = 72;
/// The float arithmetic a driver may contract: `OpFAdd`, `OpFSub`, `OpFMul`, `OpVectorTimesScalar`,
/// `OpMatrixTimesScalar`, `OpVectorTimesMatrix`, `OpMatrixTimesVector`, `OpMatrixTimesMatrix`, `OpDot`.
const CONTRACTIBLE: [u32; 9] = [129, 131, 133, 142, 143, 144, 145, 146, 148];
/// The `NoContraction` decoration.
const NO_CONTRACTION: u32 = 42;
/// `OpFunction` and `OpFunctionEnd`.
const OP_FUNCTION: u32 = 54;
const OP_FUNCTION_END: u32 = 56;
/// The functions of `trace.wgsl` whose arithmetic must round as the CPU's does, operation by operation: the
/// watertight triangle test and its exact edge functions.
const EXACT_FUNCTIONS: [&str; 2] = ["intersect_triangle", "exact_difference"];
/// The instruction set whose float `min`, `max` and `clamp` naga writes.
const GLSL_STD_450: &[u8] = b"GLSL.std.450";
/// GLSL.std.450's `FMin`, `FMax`, `FClamp` and the NaN-ignoring instruction each becomes.
const NAN_IGNORING: [(u32, u32); 3] = [(37, 79), (40, 80), (43, 81)];
/// Words of the SPIR-V header before the first instruction.
const HEADER_WORDS: usize = 5;

/// The kernel's WGSL, parsed and validated once.
pub(super) struct Source {
    /// The module.
    module: naga::Module,
    /// Its validation info.
    info: naga::valid::ModuleInfo,
}

impl Source {
    /// Parses and validates `wgsl`. The kernel's source is part of the binary, so an error is a bug: it panics
    /// with naga's message.
    pub fn new(wgsl: &str) -> Source {
        let module = naga::front::wgsl::parse_str(wgsl).unwrap_or_else(|e| panic!("{}", e.emit_to_string(wgsl)));
        let info = naga::valid::Validator::new(naga::valid::ValidationFlags::all(), naga::valid::Capabilities::all())
            .validate(&module)
            .unwrap_or_else(|e| panic!("the kernel's WGSL is invalid: {e:?}"));
        Source { module, info }
    }

    /// The SPIR-V of compute entry point `entry` with the pipeline constants `constants`, without the initializers
    /// of [`WRITTEN_BEFORE_READ`], its float `min`, `max` and `clamp` ignoring NaN operands, none of its float
    /// arithmetic contracted.
    pub fn spirv(&self, entry: &str, constants: &[(&str, f64)]) -> Vec<u32> {
        let mut words = self.written(entry, constants);
        drop_initializers(&mut words, &WRITTEN_BEFORE_READ);
        ignore_nan_operands(&mut words);
        forbid_contraction(&mut words, &EXACT_FUNCTIONS);
        words
    }

    /// The SPIR-V as naga writes it, every variable initialized.
    fn written(&self, entry: &str, constants: &[(&str, f64)]) -> Vec<u32> {
        let constants: naga::back::PipelineConstants = constants.iter().map(|&(k, v)| (k.to_owned(), v)).collect();
        let stage = Some((naga::ShaderStage::Compute, entry));
        let (module, info) =
            naga::back::pipeline_constants::process_overrides(&self.module, &self.info, stage, &constants)
                .unwrap_or_else(|e| panic!("pipeline constants of {entry}: {e}"));
        let unchecked = naga::proc::BoundsCheckPolicy::Unchecked;
        let options = spv::Options {
            // SPIR-V 1.0 runs on every Vulkan version.
            lang_version: (1, 0),
            // `OpName`s, which name the variables whose initializers go.
            flags: spv::WriterFlags::DEBUG,
            bounds_check_policies: naga::proc::BoundsCheckPolicies {
                index: unchecked,
                buffer: unchecked,
                image_load: unchecked,
                binding_array: unchecked,
            },
            force_loop_bounding: false,
            emit_int_div_checks: false,
            ..spv::Options::default()
        };
        let pipeline = spv::PipelineOptions { shader_stage: naga::ShaderStage::Compute, entry_point: entry.to_owned() };
        spv::write_vec(&module, &info, &options, Some(&pipeline))
            .unwrap_or_else(|e| panic!("writing the SPIR-V of {entry}: {e}"))
    }
}

/// The instructions of a SPIR-V module after its header: each one's opcode and operand words.
fn instructions(words: &[u32]) -> impl Iterator<Item = (usize, u32, &[u32])> {
    let mut at = HEADER_WORDS;
    std::iter::from_fn(move || {
        let first = *words.get(at)?;
        let (count, opcode) = ((first >> 16) as usize, first & 0xffff);
        let start = at;
        at += count.max(1);
        Some((start, opcode, words.get(start + 1..start + count).unwrap_or(&[])))
    })
}

/// Makes every float `min`, `max` and `clamp` (GLSL.std.450 `FMin`, `FMax`, `FClamp`, whose result WGSL and SPIR-V
/// leave undefined for a NaN operand) the `NMin`, `NMax`, `NClamp` of the same instruction set, which return the
/// other operand: Rust's `f32::min` and `f32::max`, which the CPU backend's box test relies on. The kernel can then
/// use the plain built-ins where it tested for NaN lane by lane; on an H100 that made it 6–11% faster
/// (BENCHMARKS.md, "wgpu kernel step 4"), and NVIDIA's min/max instructions ignore NaN operands anyway. Returns how
/// many instructions changed.
fn ignore_nan_operands(words: &mut [u32]) -> usize {
    let glsl: Vec<u32> = instructions(words)
        .filter(|&(_, opcode, operands)| opcode == OP_EXT_INST_IMPORT && !operands.is_empty())
        .filter(|(_, _, operands)| string_operand(&operands[1..]) == GLSL_STD_450)
        .map(|(_, _, operands)| operands[0])
        .collect();
    // `OpExtInst result-type result-id set instruction operands…`.
    let calls: Vec<usize> = instructions(words)
        .filter(|&(_, opcode, operands)| opcode == OP_EXT_INST && operands.len() >= 4 && glsl.contains(&operands[2]))
        .map(|(at, _, _)| at + 4)
        .collect();
    let mut changed = 0;
    for at in calls {
        if let Some(&(_, nan_ignoring)) = NAN_IGNORING.iter().find(|&&(undefined, _)| undefined == words[at]) {
            words[at] = nan_ignoring;
            changed += 1;
        }
    }
    changed
}

/// Decorates the result of every [`CONTRACTIBLE`] instruction of the functions named `functions` `NoContraction`,
/// so that each rounds on its own as on the CPU; the decorations go before the module's first (its annotations'
/// section). Returns how many results were decorated.
fn forbid_contraction(words: &mut Vec<u32>, functions: &[&str]) -> usize {
    let named = ids_named(words, functions);
    let mut inside = false;
    // `OpFunction result-type result-id …` … `OpFunctionEnd`; `OpFAdd result-type result-id operands…`, and the
    // same for the others.
    let results: Vec<u32> = instructions(words)
        .filter(|&(_, opcode, operands)| {
            match opcode {
                OP_FUNCTION => inside = operands.len() >= 2 && named.contains(&operands[1]),
                OP_FUNCTION_END => inside = false,
                _ => {}
            }
            inside && CONTRACTIBLE.contains(&opcode) && operands.len() >= 2
        })
        .map(|(_, _, operands)| operands[1])
        .collect();
    let annotations = instructions(words)
        .find(|&(_, opcode, _)| opcode == OP_DECORATE || opcode == OP_MEMBER_DECORATE)
        .map(|(at, _, _)| at)
        .expect("the kernel's bindings are decorated");
    let decorations = results.iter().flat_map(|&id| [(3 << 16) | OP_DECORATE, id, NO_CONTRACTION]);
    words.splice(annotations..annotations, decorations);
    results.len()
}

/// A string operand's text (nul-terminated, little-endian words).
fn string_operand(words: &[u32]) -> Vec<u8> {
    let bytes: Vec<u8> = words.iter().flat_map(|w| w.to_le_bytes()).collect();
    bytes.split(|&b| b == 0).next().unwrap_or_default().to_vec()
}

/// The ids whose `OpName` is one of `names`.
fn ids_named(words: &[u32], names: &[&str]) -> Vec<u32> {
    instructions(words)
        .filter(|&(_, opcode, operands)| opcode == OP_NAME && !operands.is_empty())
        .filter(|(_, _, operands)| names.iter().any(|n| n.as_bytes() == string_operand(&operands[1..])))
        .map(|(_, _, operands)| operands[0])
        .collect()
}

/// Drops the initializer operand of every `OpVariable` whose `OpName` is one of `names`; returns how many went.
fn drop_initializers(words: &mut Vec<u32>, names: &[&str]) -> usize {
    let named = ids_named(words, names);
    // `OpVariable result-type result-id storage-class [initializer]`: 5 words with an initializer.
    let initialized: Vec<usize> = instructions(words)
        .filter(|&(_, opcode, operands)| opcode == OP_VARIABLE && operands.len() == 4 && named.contains(&operands[1]))
        .map(|(at, _, _)| at)
        .collect();
    for &at in initialized.iter().rev() {
        words.remove(at + 4);
        words[at] = (4 << 16) | OP_VARIABLE;
    }
    initialized.len()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::backend::wgpu::kernel::SOURCE;

    /// The variables of `words` that have an initializer, by name.
    fn initialized(words: &[u32]) -> Vec<String> {
        let names: Vec<(u32, String)> = instructions(words)
            .filter(|&(_, opcode, _)| opcode == OP_NAME)
            .map(|(_, _, operands)| {
                (operands[0], String::from_utf8_lossy(&string_operand(&operands[1..])).into_owned())
            })
            .collect();
        instructions(words)
            .filter(|&(_, opcode, operands)| opcode == OP_VARIABLE && operands.len() == 4)
            .filter_map(|(_, _, operands)| names.iter().find(|(id, _)| *id == operands[1]).map(|(_, n)| n.clone()))
            .collect()
    }

    #[test]
    fn only_the_arrays_written_before_read_lose_their_initializers() {
        let source = Source::new(SOURCE);
        let constants = [("LEVELS", 1.0), ("MOTION", 0.0), ("QUERY_KIND", 0.0), ("FULL_HITS", 0.0)];
        let before = initialized(&source.written("trace", &constants));
        let stripped = source.spirv("trace", &constants);
        let after = initialized(&stripped);
        for name in WRITTEN_BEFORE_READ {
            assert!(before.iter().any(|n| n == name), "naga initializes {name}");
            assert!(!after.iter().any(|n| n == name), "{name} keeps its initializer");
        }
        // Every other variable keeps its own (the hit collector's state among them).
        let kept: Vec<&String> = before.iter().filter(|n| !WRITTEN_BEFORE_READ.contains(&n.as_str())).collect();
        assert!(kept.iter().any(|n| *n == "hit_count"));
        assert_eq!(after.iter().collect::<Vec<_>>(), kept);
        // The instruction stream still ends exactly at the end of the words.
        let (last, _, operands) = instructions(&stripped).last().unwrap();
        assert_eq!(last + 1 + operands.len(), stripped.len());
    }

    /// The GLSL.std.450 instruction numbers of `words`' extended instructions, in order.
    fn glsl_calls(words: &[u32]) -> Vec<u32> {
        instructions(words)
            .filter(|&(_, opcode, operands)| opcode == OP_EXT_INST && operands.len() >= 4)
            .map(|(_, _, operands)| operands[3])
            .collect()
    }

    /// The results of `words`' contractible instructions, by the name of the function they are in.
    fn arithmetic_by_function(words: &[u32]) -> Vec<(String, u32)> {
        let names: Vec<(u32, String)> = instructions(words)
            .filter(|&(_, opcode, _)| opcode == OP_NAME)
            .map(|(_, _, operands)| {
                (operands[0], String::from_utf8_lossy(&string_operand(&operands[1..])).into_owned())
            })
            .collect();
        let mut function = String::new();
        let mut results = Vec::new();
        for (_, opcode, operands) in instructions(words) {
            if opcode == OP_FUNCTION {
                function = names.iter().find(|(id, _)| *id == operands[1]).map(|(_, n)| n.clone()).unwrap_or_default();
            } else if CONTRACTIBLE.contains(&opcode) {
                results.push((function.clone(), operands[1]));
            }
        }
        results
    }

    #[test]
    fn the_triangle_tests_float_arithmetic_and_nothing_else_is_decorated_no_contraction_once() {
        let source = Source::new(SOURCE);
        let constants = [("LEVELS", 1.0), ("MOTION", 1.0), ("QUERY_KIND", 3.0), ("FULL_HITS", 1.0)];
        let written = source.written("trace", &constants);
        let mut words = written.clone();
        let decorated = forbid_contraction(&mut words, &EXACT_FUNCTIONS);
        let arithmetic = arithmetic_by_function(&words);
        let mut expected: Vec<u32> =
            arithmetic.iter().filter(|(f, _)| EXACT_FUNCTIONS.contains(&f.as_str())).map(|&(_, id)| id).collect();
        let mut no_contraction: Vec<u32> = instructions(&words)
            .filter(|&(_, opcode, operands)| opcode == OP_DECORATE && operands[1] == NO_CONTRACTION)
            .map(|(_, _, operands)| operands[0])
            .collect();
        // The edge functions alone are six multiplies and three subtractions, their exact forms two and three more;
        // the box tests' arithmetic elsewhere is left as it was.
        assert!(decorated >= 14 && decorated < arithmetic.len(), "{decorated} of {}", arithmetic.len());
        for function in EXACT_FUNCTIONS {
            assert!(arithmetic.iter().any(|(f, _)| f == function), "no arithmetic found in {function}");
        }
        no_contraction.sort_unstable();
        expected.sort_unstable();
        assert_eq!(no_contraction, expected);
        // Nothing else changed: the old words follow once the decorations are taken out again.
        let at = instructions(&words).find(|&(_, opcode, _)| opcode == OP_DECORATE).unwrap().0;
        let mut undone = words.clone();
        undone.drain(at..at + 3 * decorated);
        assert!(undone == written);
        // Every decoration is in the annotations' section: before the first type, constant or variable.
        let first_type = instructions(&words).position(|(_, opcode, _)| (19..=39).contains(&opcode)).unwrap();
        let last_decoration = instructions(&words).enumerate().filter(|(_, (_, opcode, _))| *opcode == OP_DECORATE);
        assert!(last_decoration.last().unwrap().0 < first_type);
    }

    #[test]
    fn every_float_min_max_and_clamp_ignores_nan_operands_and_nothing_else_changes() {
        let source = Source::new(SOURCE);
        let constants = [("LEVELS", 1.0), ("MOTION", 1.0), ("QUERY_KIND", 0.0), ("FULL_HITS", 1.0)];
        let written = source.written("trace", &constants);
        let before = glsl_calls(&written);
        let mut words = written.clone();
        let changed = ignore_nan_operands(&mut words);
        let after = glsl_calls(&words);
        // The box test narrows slabs with `max` and `min`; a key time is clamped.
        assert!(changed >= 3, "{changed} instructions changed");
        for (undefined, nan_ignoring) in NAN_IGNORING {
            assert!(!after.contains(&undefined), "GLSL.std.450 {undefined} is left");
            let count = |calls: &[u32], op: u32| calls.iter().filter(|&&c| c == op).count();
            assert_eq!(count(&after, nan_ignoring), count(&before, undefined) + count(&before, nan_ignoring));
        }
        assert!(after.contains(&80) && after.contains(&79), "NMax and NMin are used");
        // Only those instruction numbers differ, word for word.
        let differing: Vec<usize> = (0..words.len()).filter(|&i| words[i] != written[i]).collect();
        assert_eq!(differing.len(), changed);
        assert_eq!(before.len(), after.len());
    }
}
