//! Writing a blob: the accels below the root that are not external, each once, children first, then the header.

use std::collections::HashMap;
use std::sync::Arc;

use super::entry::{self, EXTERNAL_BIT, ExternalRecord};
use super::header::{HEADER_BYTES, Header};
use super::wire::put_array;
use crate::context::{Accel, Context};
use crate::error::{Error, Result};

/// Bytes reserved for an entry besides its accel's size.
const ENTRY_BYTES: u64 = 256;

/// Serializes `root` and every accel below it that is not one of `external`.
pub(crate) fn blob(context: &Context, root: &Arc<Accel>, external: &[Arc<Accel>]) -> Result<Vec<u8>> {
    let device = context.device().info().kind;
    for (what, accel) in std::iter::once(("the accel", root)).chain(external.iter().map(|e| ("an external accel", e))) {
        if accel.backend_kind() != device {
            return Err(Error::FailedPrecondition(format!(
                "{what} (accel {}) is a {:?} accel; this context's device is {device:?}",
                accel.handle().0,
                accel.backend_kind()
            )));
        }
    }
    if external.len() >= EXTERNAL_BIT as usize {
        return Err(Error::InvalidExternal(format!("{} given, at most {} allowed", external.len(), EXTERNAL_BIT - 1)));
    }
    root.check_latest()?;
    let mut refs: HashMap<*const Accel, u32> = HashMap::with_capacity(external.len());
    for (index, accel) in external.iter().enumerate() {
        refs.entry(Arc::as_ptr(accel)).or_insert(EXTERNAL_BIT | index as u32);
    }
    if refs.contains_key(&Arc::as_ptr(root)) {
        return Err(Error::InvalidExternal(format!("the accel serialized (accel {}) is one of them", root.handle().0)));
    }
    let mut order = Vec::new();
    children_first(root, &mut refs, &mut order);
    let estimate: u64 = order.iter().map(|a| a.info().size_bytes + ENTRY_BYTES).sum();
    let mut out = Vec::with_capacity(HEADER_BYTES + usize::try_from(estimate).unwrap_or(0));
    out.resize(HEADER_BYTES, 0);
    put_array(&mut out, &external.iter().map(|e| ExternalRecord::of(e)).collect::<Vec<_>>());
    for accel in &order {
        entry::write(&mut out, accel, &refs)?;
    }
    let layout = context.backend().layout_version();
    Header::new(device, layout, order.len() as u32, external.len() as u32).seal(&mut out);
    Ok(out)
}

/// Appends to `order` the accels below `accel` (and `accel` itself) that `refs` does not name yet, children
/// before their parents, and names each in `refs` by its position there.
fn children_first<'a>(accel: &'a Arc<Accel>, refs: &mut HashMap<*const Accel, u32>, order: &mut Vec<&'a Arc<Accel>>) {
    for child in accel.children() {
        if !refs.contains_key(&Arc::as_ptr(child)) {
            children_first(child, refs, order);
        }
    }
    refs.insert(Arc::as_ptr(accel), order.len() as u32);
    order.push(accel);
}
