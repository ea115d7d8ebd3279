//! Pinhole cameras and the rule that places the default camera.
//!
//! The default rule, shared by `render` and `bench` (and the one the Embree
//! figures of `shared/docs/anchors.md` were measured with): the eye sits
//! inside the scene box at `centre - 0.3 * extent`, looking at the centre.
//! Game levels inside a sky box and rooms are closed shells, so a camera
//! outside the box would see only the shell; from inside, it looks across
//! the contents. The up axis is the scene's shortest axis unless given.

use anyhow::{Context, bail};
use rebraid::glam::Vec3;
use rebraid::{Aabb, Ray};

/// A pinhole camera.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    pub eye: Vec3,
    pub target: Vec3,
    pub up: Vec3,
    /// Vertical field of view in degrees.
    pub fov_deg: f32,
}

/// Which world axis points up.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum UpAxis {
    /// The scene box's shortest axis.
    #[default]
    Auto,
    X,
    Y,
    Z,
}

impl UpAxis {
    pub fn resolve(self, bounds: &Aabb) -> Vec3 {
        match self {
            UpAxis::X => Vec3::X,
            UpAxis::Y => Vec3::Y,
            UpAxis::Z => Vec3::Z,
            UpAxis::Auto => {
                let e = bounds.extent();
                if e.y <= e.x && e.y <= e.z {
                    Vec3::Y
                } else if e.z <= e.x {
                    Vec3::Z
                } else {
                    Vec3::X
                }
            }
        }
    }
}

impl Camera {
    /// The default camera of a scene (see the module docs).
    pub fn fit(bounds: &Aabb, up: Vec3) -> Self {
        let c = bounds.center();
        Self {
            eye: c - 0.3 * bounds.extent(),
            target: c,
            up,
            fov_deg: 60.0,
        }
    }

    /// Parse `eye_x,eye_y,eye_z,target_x,target_y,target_z,fov`.
    pub fn parse(s: &str, up: Vec3) -> anyhow::Result<Self> {
        let v: Vec<f32> = s
            .split(',')
            .map(|x| x.trim().parse::<f32>())
            .collect::<Result<_, _>>()
            .with_context(|| format!("--camera '{s}': expected 7 comma-separated numbers"))?;
        if v.len() != 7 || v.iter().any(|x| !x.is_finite()) {
            bail!(
                "--camera '{s}': expected 7 finite numbers eye_x,eye_y,eye_z,target_x,target_y,target_z,fov"
            );
        }
        let cam = Self {
            eye: Vec3::new(v[0], v[1], v[2]),
            target: Vec3::new(v[3], v[4], v[5]),
            up,
            fov_deg: v[6],
        };
        if cam.eye == cam.target {
            bail!("--camera '{s}': eye and target coincide");
        }
        if !(cam.fov_deg > 0.0 && cam.fov_deg < 180.0) {
            bail!("--camera '{s}': fov must be in (0, 180) degrees");
        }
        Ok(cam)
    }

    /// `eye_x,eye_y,eye_z,target_x,target_y,target_z,fov`, as `--camera` takes it.
    pub fn to_arg(&self) -> String {
        let (e, t) = (self.eye, self.target);
        format!(
            "{},{},{},{},{},{},{}",
            e.x, e.y, e.z, t.x, t.y, t.z, self.fov_deg
        )
    }

    /// Orthonormal frame (right, up, forward); copes with `up` parallel to the view.
    fn frame(&self) -> (Vec3, Vec3, Vec3) {
        let f = (self.target - self.eye).normalize();
        let mut r = f.cross(self.up);
        if r.length_squared() < 1e-12 {
            r = f.any_orthonormal_vector();
        }
        let r = r.normalize();
        (r, r.cross(f), f)
    }

    /// A generator of primary rays for an image of `width` x `height`.
    pub fn rays(&self, width: u32, height: u32) -> CameraRays {
        let (r, u, f) = self.frame();
        let h = (self.fov_deg.to_radians() * 0.5).tan();
        let aspect = width as f32 / height as f32;
        CameraRays {
            eye: self.eye,
            right: r * (h * aspect),
            up: u * h,
            forward: f,
            width,
            height,
        }
    }
}

/// Primary rays of one camera and image size.
#[derive(Clone, Copy, Debug)]
pub struct CameraRays {
    eye: Vec3,
    right: Vec3,
    up: Vec3,
    forward: Vec3,
    pub width: u32,
    pub height: u32,
}

impl CameraRays {
    /// The ray through image point (`x`, `y`) in pixels (0,0 = top left).
    #[inline]
    pub fn ray(&self, x: f32, y: f32) -> Ray {
        let sx = 2.0 * x / self.width as f32 - 1.0;
        let sy = 1.0 - 2.0 * y / self.height as f32;
        let d = (self.forward + self.right * sx + self.up * sy).normalize();
        Ray::infinite(self.eye, d)
    }

    /// The ray through the centre of pixel (`px`, `py`).
    #[inline]
    pub fn pixel_ray(&self, px: u32, py: u32) -> Ray {
        self.ray(px as f32 + 0.5, py as f32 + 0.5)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parse_round_trips_and_rejects() {
        let c = Camera::parse("1,2,3,4,5,6,45", Vec3::Y).unwrap();
        assert_eq!(Camera::parse(&c.to_arg(), Vec3::Y).unwrap(), c);
        assert!(Camera::parse("1,2,3", Vec3::Y).is_err());
        assert!(Camera::parse("1,2,3,1,2,3,45", Vec3::Y).is_err());
        assert!(Camera::parse("0,0,0,1,0,0,200", Vec3::Y).is_err());
        assert!(Camera::parse("0,0,nan,1,0,0,60", Vec3::Y).is_err());
    }

    #[test]
    fn centre_pixel_looks_at_target() {
        let c = Camera::parse("0,0,0,0,0,-5,60", Vec3::Y).unwrap();
        let r = c.rays(101, 51).pixel_ray(50, 25);
        assert!((r.dir - Vec3::new(0.0, 0.0, -1.0)).length() < 1e-6);
        let top = c.rays(100, 100).ray(50.0, 0.0);
        assert!(top.dir.y > 0.0);
    }

    #[test]
    fn auto_up_is_shortest_axis() {
        let b = Aabb::new(Vec3::ZERO, Vec3::new(10.0, 10.0, 3.0));
        assert_eq!(UpAxis::Auto.resolve(&b), Vec3::Z);
        let b = Aabb::new(Vec3::ZERO, Vec3::new(10.0, 2.0, 30.0));
        assert_eq!(UpAxis::Auto.resolve(&b), Vec3::Y);
    }
}
