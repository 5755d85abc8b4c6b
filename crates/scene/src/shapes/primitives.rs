//! Mitsuba's built-in triangle primitives, in object space.

use glam::{Vec2, Vec3};

use crate::desc::TriangleMesh;

/// Mitsuba's `rectangle`: the square [-1,1]^2 at z=0, normal +z, uv = (x+1)/2,
/// (y+1)/2 (so uv (0,0) is at (-1,-1)); triangles {1,2,0} and {1,3,2}.
pub(crate) fn rectangle() -> TriangleMesh {
    TriangleMesh {
        positions: vec![
            Vec3::new(-1.0, -1.0, 0.0),
            Vec3::new(1.0, -1.0, 0.0),
            Vec3::new(-1.0, 1.0, 0.0),
            Vec3::new(1.0, 1.0, 0.0),
        ],
        normals: Some(vec![Vec3::Z; 4]),
        uvs: Some(vec![
            Vec2::new(0.0, 0.0),
            Vec2::new(1.0, 0.0),
            Vec2::new(0.0, 1.0),
            Vec2::new(1.0, 1.0),
        ]),
        indices: vec![[1, 2, 0], [1, 3, 2]],
        flip_normals: false,
    }
}

/// Mitsuba's `cube`: [-1,1]^3 with 4 vertices per face (24 in all) carrying
/// the outward face normal and the uv pattern (0,1),(1,1),(1,0),(0,0);
/// triangles {4s,4s+1,4s+2} and {4s+3,4s,4s+2}, faces in Mitsuba's order
/// -y, +y, +x, +z, -x, -z.
pub(crate) fn cube() -> TriangleMesh {
    const SIDE_NORMALS: [[f32; 3]; 6] = [
        [0.0, -1.0, 0.0],
        [0.0, 1.0, 0.0],
        [1.0, 0.0, 0.0],
        [0.0, 0.0, 1.0],
        [-1.0, 0.0, 0.0],
        [0.0, 0.0, -1.0],
    ];
    const SIDE_UV: [[f32; 2]; 4] = [[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]];
    // Corner c sits at (+-1,+-1,+-1); bit k of c selects the sign of axis k.
    const POSITION_INDEX: [u32; 24] = [
        1, 5, 4, 0, 3, 2, 6, 7, 1, 3, 7, 5, 5, 7, 6, 4, 4, 6, 2, 0, 3, 1, 0, 2,
    ];
    let corner = |c: u32| {
        Vec3::new(
            if c & 1 != 0 { 1.0 } else { -1.0 },
            if c & 2 != 0 { 1.0 } else { -1.0 },
            if c & 4 != 0 { 1.0 } else { -1.0 },
        )
    };
    let mut mesh = TriangleMesh {
        normals: Some(Vec::new()),
        uvs: Some(Vec::new()),
        ..Default::default()
    };
    for (s, n) in SIDE_NORMALS.iter().enumerate() {
        let v = 4 * s as u32;
        for k in 0..4 {
            mesh.positions.push(corner(POSITION_INDEX[v as usize + k]));
            mesh.normals.as_mut().unwrap().push(Vec3::from_array(*n));
            mesh.uvs
                .as_mut()
                .unwrap()
                .push(Vec2::from_array(SIDE_UV[k]));
        }
        mesh.indices.push([v, v + 1, v + 2]);
        mesh.indices.push([v + 3, v, v + 2]);
    }
    mesh
}

#[cfg(test)]
mod tests {
    use super::*;

    fn face_normal(m: &TriangleMesh, t: usize) -> Vec3 {
        let [a, b, c] = m.indices[t].map(|i| m.positions[i as usize]);
        (b - a).cross(c - a).normalize()
    }

    #[test]
    fn rectangle_winding_agrees_with_plus_z_normal_and_uv_origin_at_minus_one() {
        let r = rectangle();
        for t in 0..2 {
            assert!((face_normal(&r, t) - Vec3::Z).length() < 1e-6);
        }
        let i = r
            .positions
            .iter()
            .position(|p| *p == Vec3::new(-1.0, -1.0, 0.0))
            .unwrap();
        assert_eq!(r.uvs.as_ref().unwrap()[i], Vec2::ZERO);
        let j = r
            .positions
            .iter()
            .position(|p| *p == Vec3::new(1.0, 1.0, 0.0))
            .unwrap();
        assert_eq!(r.uvs.as_ref().unwrap()[j], Vec2::ONE);
    }

    #[test]
    fn cube_faces_point_outward_and_match_vertex_normals() {
        let c = cube();
        assert_eq!(c.positions.len(), 24);
        assert_eq!(c.indices.len(), 12);
        for t in 0..12 {
            let n = face_normal(&c, t);
            let [a, b, cc] = c.indices[t].map(|i| c.positions[i as usize]);
            let centroid = (a + b + cc) / 3.0;
            assert!(n.dot(centroid) > 0.0, "triangle {t} faces inward");
            for i in c.indices[t] {
                assert!((c.normals.as_ref().unwrap()[i as usize] - n).length() < 1e-6);
            }
            // All vertices of a face lie on the plane n.p = 1.
            assert!((n.dot(a) - 1.0).abs() < 1e-6);
        }
    }
}
