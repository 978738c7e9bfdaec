//! Reading a blob: the header, the external accels given against what the blob recorded of them, then each
//! entry in turn, made into an accel of the context over the accels before it. A failure takes back every accel
//! already made.
//!
//! An external accel of the recorded kind whose bounds differ from the recorded ones (a newer version of the
//! accel the blob was made over, as when a parent is restored after its child was updated) is accepted, but the
//! instance accels built over it (directly or through transforms, which are rebuilt over it) are marked stale:
//! their boxes may not hold it, so they refuse traces until they are updated.

use std::sync::Arc;

use super::entry::{EXTERNAL_BIT, Entry, ExternalRecord, kind_of};
use super::header::{HEADER_BYTES, Header};
use super::wire::{Reader, invalid};
use crate::accel::AccelKind;
use crate::context::{Accel, Context};
use crate::error::{Error, Result};
use crate::geometry::MAX_GRAPH_DEPTH;

/// Creates in `context` every accel `blob` embeds, children first, over the `external` accels it refers to.
pub(crate) fn accels(context: &Context, blob: &[u8], external: &[Arc<Accel>]) -> Result<Vec<Arc<Accel>>> {
    let header = Header::read(blob)?;
    let device = context.device().info().kind;
    header.check_backend(device, context.backend().layout_version())?;
    if external.len() != header.external as usize {
        return Err(Error::InvalidExternal(format!(
            "{} given, the blob refers to {}",
            external.len(),
            header.external
        )));
    }
    let mut reader = Reader::new(&blob[HEADER_BYTES..]);
    let records: Vec<ExternalRecord> = reader.array("external accels")?;
    if records.len() != external.len() {
        return Err(invalid(format!("{} external records, the header counts {}", records.len(), external.len())));
    }
    let mut graph = Graph { context, made: Vec::new(), external: Vec::with_capacity(external.len()) };
    for (index, (accel, record)) in external.iter().zip(&records).enumerate() {
        let moved = check_external(index, accel, record, context)?;
        graph.external.push((Arc::clone(accel), moved));
    }
    for index in 0..header.accels as usize {
        let made = Entry::read(&mut reader, index, external.len())
            .and_then(|entry| graph.make(entry))
            .map_err(|e| within(index, e))?;
        graph.made.push(made);
    }
    reader.finish("the payload")?;
    Ok(graph.keep())
}

/// Checks external accel `index` against what the blob recorded of it: where `context`'s device reads it
/// (FAILED_PRECONDITION otherwise) and of the recorded kind (INVALID_ARGUMENT otherwise). Returns whether its
/// bounds differ from the recorded ones.
fn check_external(index: usize, accel: &Accel, record: &ExternalRecord, context: &Context) -> Result<bool> {
    if !context.shares_memory_with(accel) {
        return Err(Error::FailedPrecondition(format!(
            "external accel {index} (accel {}) is a {:?} accel of another device; this context's device is {:?}",
            accel.handle().0,
            accel.backend_kind(),
            context.device().info().kind
        )));
    }
    let given = ExternalRecord::of(accel);
    if given.kind != record.kind {
        return Err(Error::InvalidExternal(format!(
            "external accel {index} (accel {}) is a {:?} accel; the blob was made over a {:?} accel",
            accel.handle().0,
            accel.info().kind,
            kind_of(record.kind)?
        )));
    }
    Ok(!given.same_bounds(record))
}

/// The accels a blob's entries may place: those made from it so far (destroyed again, last first, unless kept)
/// and the external ones, each with whether its bounds may differ from those the blob's accels were built over.
struct Graph<'a> {
    /// The context they are made in.
    context: &'a Context,
    /// The accels made, in the blob's order.
    made: Vec<(Arc<Accel>, bool)>,
    /// The external accels.
    external: Vec<(Arc<Accel>, bool)>,
}

impl Graph<'_> {
    /// Makes the accel of `entry` over the accels its child references name (checked by [`Entry::read`]).
    fn make(&self, entry: Entry<'_>) -> Result<(Arc<Accel>, bool)> {
        let (children, moved): (Vec<Arc<Accel>>, Vec<bool>) = entry
            .children
            .iter()
            .map(|&code| {
                let (accel, moved) = match code & EXTERNAL_BIT {
                    0 => &self.made[code as usize],
                    _ => &self.external[(code & !EXTERNAL_BIT) as usize],
                };
                (Arc::clone(accel), *moved)
            })
            .unzip();
        let deepest = children.iter().map(|c| c.info().depth).max().unwrap_or(0);
        if deepest >= MAX_GRAPH_DEPTH {
            return Err(invalid(format!(
                "it would head a graph of {} levels, more than {MAX_GRAPH_DEPTH}",
                u64::from(deepest) + 1
            )));
        }
        let backend = self.context.backend();
        let data = match (entry.shape.kind, &entry.transform, children.as_slice()) {
            (AccelKind::Triangles | AccelKind::Instances, _, _) => {
                backend.decode(&entry.shape, &entry.options, entry.payload, &children)?
            }
            (_, Some(transform), [child]) if entry.payload.is_empty() => backend.build_transform(transform, child)?,
            _ => return Err(invalid("a transform with a backend payload")),
        };
        let kind = entry.shape.kind;
        let accel = self.context.register(entry.shape, &entry.options, data, children, entry.retained)?;
        let over_moved = moved.contains(&true);
        if over_moved && kind == AccelKind::Instances {
            self.context.mark_stale(&accel);
        }
        // A transform is rebuilt over its child: its bounds follow the child's.
        Ok((accel, over_moved && kind.is_transform()))
    }

    /// Keeps the accels made.
    fn keep(mut self) -> Vec<Arc<Accel>> {
        std::mem::take(&mut self.made).into_iter().map(|(accel, _)| accel).collect()
    }
}

impl Drop for Graph<'_> {
    fn drop(&mut self) {
        while let Some((accel, _)) = self.made.pop() {
            // Nothing but accels made after it places it, and those are gone: it can be destroyed.
            let _ = self.context.destroy_accel(accel.handle());
        }
    }
}

/// `error`, when it is about the blob, said to be about accel `index`.
fn within(index: usize, error: Error) -> Error {
    match error {
        Error::InvalidBlob(what) => Error::InvalidBlob(format!("accel {index}: {what}")),
        other => other,
    }
}
