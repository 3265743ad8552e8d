//! A depth map as a triangle mesh, written as binary little-endian PLY (vertices with normals,
//! faces between 4-connected object pixels).

use crate::camera::Intrinsics;

/// Vertices (mm), per-vertex unit normals and triangles (vertex indices).
pub type Mesh = (Vec<[f32; 3]>, Vec<[f32; 3]>, Vec<[u32; 3]>);

/// Vertices (camera frame, mm), per-vertex normals and triangles of the masked depth map: two
/// triangles per 2×2 block of object pixels (one where only three are on the object), wound
/// so that they face the camera.
pub fn depth_mesh(
    intr: &Intrinsics,
    width: usize,
    depth_mm: &[f32],
    normals: &[[f32; 3]],
    mask: &[bool],
) -> Mesh {
    let n = depth_mm.len();
    let height = n / width.max(1);
    let mut index = vec![u32::MAX; n];
    let mut vertices = Vec::new();
    let mut vnormals = Vec::new();
    for p in 0..n {
        let z = depth_mm[p];
        if !mask[p] || !z.is_finite() || z <= 0.0 {
            continue;
        }
        let r = intr.ray((p % width) as f64, (p / width) as f64);
        let s = f64::from(z) / r[2];
        index[p] = vertices.len() as u32;
        vertices.push([(r[0] * s) as f32, (r[1] * s) as f32, z]);
        vnormals.push(normals[p]);
    }
    let mut faces = Vec::new();
    for y in 0..height.saturating_sub(1) {
        for x in 0..width.saturating_sub(1) {
            let [a, b, c, d] = [
                index[y * width + x],
                index[y * width + x + 1],
                index[(y + 1) * width + x],
                index[(y + 1) * width + x + 1],
            ];
            // Image y points down and the camera looks along +z, so (a, c, b) is
            // counter-clockwise seen from the camera.
            match (a != u32::MAX, b != u32::MAX, c != u32::MAX, d != u32::MAX) {
                (true, true, true, true) => {
                    faces.push([a, c, b]);
                    faces.push([b, c, d]);
                }
                (true, true, true, false) => faces.push([a, c, b]),
                (true, true, false, true) => faces.push([a, d, b]),
                (true, false, true, true) => faces.push([a, c, d]),
                (false, true, true, true) => faces.push([b, c, d]),
                _ => {}
            }
        }
    }
    (vertices, vnormals, faces)
}

/// Binary little-endian PLY with `x y z nx ny nz` vertices and triangle faces.
pub fn encode_ply_mesh(vertices: &[[f32; 3]], normals: &[[f32; 3]], faces: &[[u32; 3]]) -> Vec<u8> {
    let header = format!(
        "ply\nformat binary_little_endian 1.0\ncomment murk photometric stereo, camera frame, mm\n\
         element vertex {}\nproperty float x\nproperty float y\nproperty float z\n\
         property float nx\nproperty float ny\nproperty float nz\n\
         element face {}\nproperty list uchar uint vertex_indices\nend_header\n",
        vertices.len(),
        faces.len()
    );
    let mut out = Vec::with_capacity(header.len() + vertices.len() * 24 + faces.len() * 13);
    out.extend_from_slice(header.as_bytes());
    for (v, n) in vertices.iter().zip(normals) {
        for c in v.iter().chain(n) {
            out.extend_from_slice(&c.to_le_bytes());
        }
    }
    for f in faces {
        out.push(3);
        for i in f {
            out.extend_from_slice(&i.to_le_bytes());
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_full_grid_gives_two_faces_per_block_facing_the_camera() {
        let intr = Intrinsics::new(10.0, 10.0, 1.0, 1.0);
        let (w, h) = (3, 3);
        let depth = vec![100.0f32; w * h];
        let mut mask = vec![true; w * h];
        let normals = vec![[0.0, 0.0, -1.0]; w * h];
        let (v, _, f) = depth_mesh(&intr, w, &depth, &normals, &mask);
        assert_eq!((v.len(), f.len()), (9, 8));
        for tri in &f {
            let [a, b, c] = tri.map(|i| v[i as usize]);
            let e1 = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
            let e2 = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
            let nz = e1[0] * e2[1] - e1[1] * e2[0];
            assert!(nz < 0.0, "face {tri:?} faces away from the camera");
        }
        mask[4] = false;
        let (v, _, f) = depth_mesh(&intr, w, &depth, &normals, &mask);
        assert_eq!((v.len(), f.len()), (8, 4));
        let ply = encode_ply_mesh(&v, &vec![[0.0; 3]; v.len()], &f);
        let text = String::from_utf8_lossy(&ply[..ply.len().min(400)]);
        assert!(text.contains("element vertex 8") && text.contains("element face 4"));
        let header_len = text.find("end_header\n").unwrap() + "end_header\n".len();
        assert_eq!(ply.len(), header_len + 8 * 24 + 4 * 13);
    }
}
