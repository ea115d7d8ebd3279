//! Affine instance transforms.

use glam::{Affine3A, Vec3};

use crate::{Aabb, Error};

/// Accept a transform only when it is finite and invertible with a finite
/// inverse (rejects zero scale, NaN and infinities).
pub fn check_transform(t: &Affine3A) -> Result<(), Error> {
    if !t.is_finite() {
        return Err(Error::InvalidTransform("non-finite entry"));
    }
    let det = t.matrix3.determinant();
    // Relative to the scale of the matrix, so that tiny but regular scales pass.
    let m = t.matrix3;
    let scale = m.x_axis.length() * m.y_axis.length() * m.z_axis.length();
    if det == 0.0 || !det.is_finite() || scale == 0.0 || (det.abs() / scale) < 1.0e-6 {
        return Err(Error::InvalidTransform(
            "singular (zero scale or collapsed axes)",
        ));
    }
    if !t.inverse().is_finite() {
        return Err(Error::InvalidTransform("inverse is not finite"));
    }
    Ok(())
}

/// World box of a transformed box: the box of its eight transformed corners
/// (Arvo's method, done with the matrix's absolute value).
#[inline]
pub fn transform_box(t: &Affine3A, b: &Aabb) -> Aabb {
    if b.is_empty() {
        return Aabb::EMPTY;
    }
    let c = t.transform_point3(b.center());
    let h = b.extent() * 0.5;
    let m = t.matrix3;
    let e = Vec3::from(m.x_axis.abs() * h.x + m.y_axis.abs() * h.y + m.z_axis.abs() * h.z);
    // Round outwards so that the box surely holds every transformed point,
    // whatever the rounding of `transform_point3`: its error scales with the
    // magnitudes of the terms it sums (linear part and translation), which
    // can far exceed the result's when the translation cancels them.
    let mag = Vec3::from(
        m.x_axis.abs() * (b.center().x.abs() + h.x)
            + m.y_axis.abs() * (b.center().y.abs() + h.y)
            + m.z_axis.abs() * (b.center().z.abs() + h.z)
            + t.translation.abs(),
    );
    let pad = (c.abs() + e + mag) * (4.0 * f32::EPSILON);
    Aabb::new(c - e - pad, c + e + pad)
}

/// Transform a normal by the inverse transpose of the linear part.
#[inline]
pub fn transform_normal(world_to_object: &Affine3A, n: Vec3) -> Vec3 {
    Vec3::from(world_to_object.matrix3.transpose() * glam::Vec3A::from(n))
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::{Quat, Vec3};

    #[test]
    fn rejects_singular_and_nan() {
        assert!(check_transform(&Affine3A::from_scale(Vec3::new(1.0, 0.0, 1.0))).is_err());
        assert!(
            check_transform(&Affine3A::from_translation(Vec3::new(f32::NAN, 0.0, 0.0))).is_err()
        );
        assert!(check_transform(&Affine3A::from_scale(Vec3::new(2.0, 0.5, 3.0))).is_ok());
    }

    #[test]
    fn transformed_box_holds_transformed_corners() {
        let t = Affine3A::from_scale_rotation_translation(
            Vec3::new(2.0, 0.5, 3.0),
            Quat::from_euler(glam::EulerRot::XYZ, 0.3, 1.1, -0.7),
            Vec3::new(10.0, -3.0, 7.0),
        );
        let b = Aabb::new(Vec3::new(-1.0, 0.0, 2.0), Vec3::new(3.0, 1.0, 5.0));
        let w = transform_box(&t, &b);
        for c in b.corners() {
            assert!(w.contains_point(t.transform_point3(c)));
        }
    }
}
