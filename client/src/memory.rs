//! Buffers whose size a caller's numbers set (rays asked for, hits and reductions coming back), allocated so that a
//! size this process cannot hold is an error ([`Error::Memory`]) where an infallible allocation would abort it.

use glam::Vec3;
use rayd_engine::format::RayFormat;
use rayd_engine::raygen::fill_random_rays;

use crate::error::{Error, Result};

/// `count` rays as [`rayd_engine::raygen::random_rays`] makes them (origins uniform in the box `[lo, hi]`,
/// directions uniform), in a buffer allocated as [`zeroed`] does.
pub fn random_rays(lo: Vec3, hi: Vec3, count: usize, seed: u64, format: RayFormat) -> Result<Vec<u8>> {
    let what = || format!("{count} {} rays", format.name());
    let mut rays = zeroed(count.saturating_mul(format.size()), what)?;
    fill_random_rays(lo, hi, seed, format, 0, &mut rays);
    Ok(rays)
}

/// A buffer of `bytes` zeros; [`Error::Memory`] naming `what` where it cannot be allocated.
fn zeroed(bytes: usize, what: impl FnOnce() -> String) -> Result<Vec<u8>> {
    let mut buffer = reserved(bytes, what)?;
    buffer.resize(bytes, 0);
    Ok(buffer)
}

/// An empty buffer with room for `bytes`; [`Error::Memory`] naming `what` where it cannot be allocated.
pub(crate) fn reserved(bytes: usize, what: impl FnOnce() -> String) -> Result<Vec<u8>> {
    let mut buffer = Vec::new();
    buffer.try_reserve_exact(bytes).map_err(|_| Error::Memory { what: what(), bytes: bytes as u64 })?;
    Ok(buffer)
}

/// Appends `piece` to `buffer`, which grows as [`reserved`] allocates; [`Error::Memory`] naming `what` (the whole
/// buffer's contents) where it cannot.
pub(crate) fn append(buffer: &mut Vec<u8>, piece: &[u8], what: impl FnOnce() -> String) -> Result<()> {
    let bytes = buffer.len().saturating_add(piece.len());
    buffer.try_reserve(piece.len()).map_err(|_| Error::Memory { what: what(), bytes: bytes as u64 })?;
    buffer.extend_from_slice(piece);
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_size_past_what_the_process_can_hold_is_an_error_naming_it() {
        let error = zeroed(usize::MAX, || "everything".into()).unwrap_err();
        assert_eq!(error.code(), tonic::Code::ResourceExhausted);
        assert!(error.to_string().starts_with(&format!("everything take {} bytes", usize::MAX)), "{error}");
        let (lo, hi) = (Vec3::ZERO, Vec3::ONE);
        let rays = random_rays(lo, hi, 3, 9, RayFormat::OriginDirection).unwrap();
        assert_eq!(rays, rayd_engine::raygen::random_rays(lo, hi, 3, 9, RayFormat::OriginDirection), "the engine's");
        let error = random_rays(lo, hi, usize::MAX / 8, 9, RayFormat::Full).unwrap_err();
        assert!(error.to_string().starts_with(&format!("{} full rays take", usize::MAX / 8)), "{error}");
        let mut buffer = zeroed(3, || unreachable!("3 bytes fit")).unwrap();
        assert_eq!(buffer, [0; 3]);
        append(&mut buffer, &[1, 2], || unreachable!("5 bytes fit")).unwrap();
        assert_eq!(buffer, [0, 0, 0, 1, 2]);
        let error = reserved(isize::MAX as usize, || "half of everything".into()).unwrap_err();
        assert!(matches!(error, Error::Memory { bytes, .. } if bytes == isize::MAX as u64), "{error}");
    }
}
