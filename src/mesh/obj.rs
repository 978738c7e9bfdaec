//! Wavefront OBJ, the part a triangle mesh needs: `v` positions and `f` faces (position indices, 1-based or negative
//! for relative; `/vt/vn` parts ignored), polygons split into fans from their first corner. Every other statement
//! (`vt`, `vn`, `o`, `g`, `usemtl`, points and lines …) is skipped. Every number and index is checked: a bad file
//! is an error naming its line, never a panic (`tobj`, used before, overflowed on some: found by fuzzing).

use glam::Vec3;

use super::Mesh;

/// Parses OBJ text into a mesh, or says which line is wrong and why.
pub(super) fn parse(text: &str) -> Result<Mesh, String> {
    let mut mesh = Mesh::default();
    let mut corners: Vec<u32> = Vec::new();
    for (number, line) in text.lines().enumerate() {
        let at_line = |e: String| format!("line {}: {e}", number + 1);
        let mut words = line.split_whitespace();
        match words.next() {
            Some("v") => mesh.positions.push(position(words).map_err(at_line)?),
            Some("f") => {
                corners.clear();
                for word in words {
                    corners.push(corner(word, mesh.positions.len()).map_err(at_line)?);
                }
                if corners.len() < 3 {
                    return Err(at_line(format!("a face needs three corners, this one has {}", corners.len())));
                }
                mesh.triangles.extend((1..corners.len() - 1).map(|i| [corners[0], corners[i], corners[i + 1]]));
            }
            _ => {}
        }
    }
    let vertices = mesh.positions.len();
    if let Some(index) = mesh.triangles.iter().flatten().find(|&&i| i as usize >= vertices) {
        return Err(format!("a face names vertex {} of {vertices}", u64::from(*index) + 1));
    }
    Ok(mesh)
}

/// The position of a `v` statement: three numbers (a fourth, the weight, is ignored).
fn position<'a>(mut numbers: impl Iterator<Item = &'a str>) -> Result<Vec3, String> {
    let mut next = || -> Result<f32, String> {
        let word = numbers.next().ok_or("a vertex needs three numbers")?;
        word.parse().map_err(|_| format!("{word:?} is not a number"))
    };
    Ok(Vec3::new(next()?, next()?, next()?))
}

/// The 0-based vertex index of a face corner `v`, `v/vt`, `v//vn` or `v/vt/vn`, with `defined` vertices so far
/// (a negative index counts back from them; a positive one may name a vertex defined later in the file).
fn corner(word: &str, defined: usize) -> Result<u32, String> {
    let v = word.split('/').next().unwrap_or_default();
    let index: i64 = v.parse().map_err(|_| format!("face corner {word:?}: {v:?} is not a vertex index"))?;
    let resolved = match index {
        1.. => Some(index - 1),
        0 => None,
        _ => i64::try_from(defined).ok().map(|defined| defined + index).filter(|&i| i >= 0),
    };
    resolved
        .and_then(|i| u32::try_from(i).ok())
        .ok_or_else(|| format!("face corner {word:?}: no vertex {index} (with {defined} defined so far)"))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn faces_index_positions_absolutely_or_relatively_and_polygons_become_fans() {
        let text = "# a quad and a triangle\nv 0 0 0\nv 1 0 0 1.0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvn 0 0 1\n\
                    o quad\nf 1/1/1 2/1/1 3//1 4\ng tri\nf -4 -3 -1\nl 1 2\n";
        let mesh = parse(text).unwrap();
        assert_eq!(mesh.positions[2], Vec3::new(1.0, 1.0, 0.0));
        assert_eq!(mesh.triangles, [[0, 1, 2], [0, 2, 3], [0, 1, 3]]);
    }

    #[test]
    fn bad_numbers_and_indices_are_errors_naming_the_line() {
        let refused = |text: &str| parse(text).unwrap_err();
        assert_eq!(refused("v 0 0\n"), "line 1: a vertex needs three numbers");
        assert_eq!(refused("v 0 0 x\n"), "line 1: \"x\" is not a number");
        let three = "v 0 0 0\nv 1 0 0\nv 0 1 0\n";
        assert_eq!(refused(&format!("{three}f 1 2\n")), "line 4: a face needs three corners, this one has 2");
        assert_eq!(
            refused(&format!("{three}f 0 1 2\n")),
            "line 4: face corner \"0\": no vertex 0 (with 3 defined so far)"
        );
        // The `meshes` fuzz target's crash in tobj (2026-11-23): a relative index before the first vertex.
        assert_eq!(
            refused(&format!("{three}f 1/-3 -4 2\n")),
            "line 4: face corner \"-4\": no vertex -4 (with 3 defined so far)"
        );
        assert_eq!(refused(&format!("{three}f 1 2 4\n")), "a face names vertex 4 of 3");
        assert_eq!(
            refused(&format!("{three}f 1 2 99999999999\n")),
            "line 4: face corner \"99999999999\": no vertex 99999999999 (with 3 defined so far)"
        );
        assert_eq!(refused(&format!("{three}f 1 2 x/1\n")), "line 4: face corner \"x/1\": \"x\" is not a vertex index");
    }
}
