//! A small deterministic ray tracer for CLEVR-like scenes: spheres, cubes and cylinders
//! standing on an infinite floor (`z = 0`) under one directional light with hard shadows.
//! Rubber is Lambertian with a faint highlight; metal adds a sharp highlight and one
//! mirror bounce. All arithmetic is f64 in a fixed order, so the same scene gives the same
//! bytes on every run and thread count.

use crate::camera::Camera;
use crate::math::Vec3;

#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Shape {
    Sphere,
    Cube,
    Cylinder,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Material {
    Rubber,
    Metal,
}

/// One object. `radius` is the CLEVR size parameter: sphere radius, cylinder radius and
/// half-height, cube half-extent. Every object rests on the floor.
#[derive(Debug, Clone, Copy)]
pub struct Object {
    pub shape: Shape,
    pub material: Material,
    /// Base colour, linear RGB in `[0, 1]`.
    pub color: Vec3,
    /// Centre of the footprint on the floor (`z` ignored).
    pub position: Vec3,
    pub radius: f64,
    /// Rotation about `z` (cubes only have a visible one).
    pub yaw: f64,
}

#[derive(Debug, Clone, Copy)]
pub struct Lighting {
    /// Unit vector pointing *towards* the light.
    pub direction: Vec3,
    pub color: Vec3,
    pub ambient: f64,
    pub floor: Vec3,
    pub sky: Vec3,
}

#[derive(Debug, Clone)]
pub struct World {
    pub objects: Vec<Object>,
    pub lighting: Lighting,
}

/// What a ray hits first.
#[derive(Debug, Clone, Copy)]
struct Hit {
    t: f64,
    normal: Vec3,
    /// `None` = floor.
    object: Option<usize>,
}

const EPS: f64 = 1e-7;

impl Object {
    /// Half-height of the object: its centre is at `z = half_height`.
    fn half_height(&self) -> f64 {
        self.radius
    }

    fn centre(&self) -> Vec3 {
        Vec3::new(self.position.x, self.position.y, self.half_height())
    }

    /// Ray–object intersection: nearest `t > EPS` and the outward normal.
    fn intersect(&self, o: Vec3, d: Vec3) -> Option<(f64, Vec3)> {
        match self.shape {
            Shape::Sphere => {
                let oc = o - self.centre();
                let b = oc.dot(d);
                let c = oc.dot(oc) - self.radius * self.radius;
                let disc = b * b - c;
                if disc < 0.0 {
                    return None;
                }
                let s = disc.sqrt();
                let t = if -b - s > EPS { -b - s } else { -b + s };
                (t > EPS).then(|| (t, ((o + d * t) - self.centre()).normalized()))
            }
            Shape::Cube => {
                // Slab test in the cube's frame (rotate by −yaw about z).
                let (s, c) = (-self.yaw).sin_cos();
                let rot = |v: Vec3| Vec3::new(c * v.x - s * v.y, s * v.x + c * v.y, v.z);
                let lo = rot(o - self.centre());
                let ld = rot(d);
                let (mut tmin, mut tmax) = (f64::NEG_INFINITY, f64::INFINITY);
                let mut axis_in = 0;
                let mut sign_in = 0.0;
                for (a, (oo, dd)) in [(lo.x, ld.x), (lo.y, ld.y), (lo.z, ld.z)]
                    .into_iter()
                    .enumerate()
                {
                    if dd.abs() < 1e-15 {
                        if oo.abs() > self.radius {
                            return None;
                        }
                        continue;
                    }
                    let t1 = (-self.radius - oo) / dd;
                    let t2 = (self.radius - oo) / dd;
                    let (near, far, sign) = if t1 < t2 {
                        (t1, t2, -1.0)
                    } else {
                        (t2, t1, 1.0)
                    };
                    if near > tmin {
                        tmin = near;
                        axis_in = a;
                        sign_in = sign;
                    }
                    tmax = tmax.min(far);
                }
                if tmin > tmax || tmin <= EPS {
                    return None;
                }
                let mut n = [0.0; 3];
                n[axis_in] = sign_in;
                // Back to world: rotate by +yaw.
                let (s, c) = self.yaw.sin_cos();
                let normal = Vec3::new(c * n[0] - s * n[1], s * n[0] + c * n[1], n[2]);
                Some((tmin, normal))
            }
            Shape::Cylinder => {
                let h = 2.0 * self.half_height();
                let p = o - Vec3::new(self.position.x, self.position.y, 0.0);
                let mut best: Option<(f64, Vec3)> = None;
                let mut consider = |t: f64, n: Vec3| {
                    if t > EPS && best.is_none_or(|(bt, _)| t < bt) {
                        best = Some((t, n));
                    }
                };
                // Side: x² + y² = r², 0 ≤ z ≤ h.
                let a = d.x * d.x + d.y * d.y;
                if a > 1e-15 {
                    let b = p.x * d.x + p.y * d.y;
                    let c = p.x * p.x + p.y * p.y - self.radius * self.radius;
                    let disc = b * b - a * c;
                    if disc >= 0.0 {
                        let s = disc.sqrt();
                        for t in [(-b - s) / a, (-b + s) / a] {
                            let z = p.z + d.z * t;
                            if (0.0..=h).contains(&z) {
                                let q = p + d * t;
                                consider(t, Vec3::new(q.x, q.y, 0.0).normalized());
                            }
                        }
                    }
                }
                // Caps.
                if d.z.abs() > 1e-15 {
                    for (z, nz) in [(h, 1.0), (0.0, -1.0)] {
                        let t = (z - p.z) / d.z;
                        let q = p + d * t;
                        if q.x * q.x + q.y * q.y <= self.radius * self.radius {
                            consider(t, Vec3::new(0.0, 0.0, nz));
                        }
                    }
                }
                best
            }
        }
    }
}

impl World {
    fn nearest(&self, o: Vec3, d: Vec3) -> Option<Hit> {
        let mut best: Option<Hit> = None;
        for (i, obj) in self.objects.iter().enumerate() {
            if let Some((t, normal)) = obj.intersect(o, d)
                && best.is_none_or(|b| t < b.t)
            {
                best = Some(Hit {
                    t,
                    normal,
                    object: Some(i),
                });
            }
        }
        if d.z < -1e-12 {
            let t = -o.z / d.z;
            if t > EPS && best.is_none_or(|b| t < b.t) {
                best = Some(Hit {
                    t,
                    normal: Vec3::Z,
                    object: None,
                });
            }
        }
        best
    }

    fn in_shadow(&self, p: Vec3) -> bool {
        let l = self.lighting.direction;
        self.objects.iter().any(|obj| obj.intersect(p, l).is_some())
    }

    /// Instance id seen along a ray: 0 for floor or sky, `k + 1` for object `k`.
    pub fn instance(&self, o: Vec3, d: Vec3) -> u8 {
        match self.nearest(o, d) {
            Some(Hit {
                object: Some(k), ..
            }) => (k + 1) as u8,
            _ => 0,
        }
    }

    /// Linear RGB along a ray; `depth` limits mirror bounces.
    pub fn shade(&self, o: Vec3, d: Vec3, depth: u32) -> Vec3 {
        let lt = &self.lighting;
        let Some(hit) = self.nearest(o, d) else {
            // Sky: brighter towards the zenith.
            return lt.sky * (0.75 + 0.25 * d.z.max(0.0));
        };
        let p = o + d * hit.t;
        let n = hit.normal;
        let p_off = p + n * 1e-6;
        let lambert = n.dot(lt.direction).max(0.0);
        let lit = if lambert > 0.0 && !self.in_shadow(p_off) {
            1.0
        } else {
            0.0
        };
        let Some(k) = hit.object else {
            // Floor: a soft radial fall-off keeps it from being one flat colour.
            let falloff = 1.0 / (1.0 + 0.004 * (p.x * p.x + p.y * p.y));
            let diffuse = lt.ambient + (1.0 - lt.ambient) * lambert * lit;
            return lt.floor.mul_elem(lt.color) * (diffuse * (0.85 + 0.15 * falloff));
        };
        let obj = &self.objects[k];
        let half = (lt.direction - d).normalized();
        let spec_angle = n.dot(half).max(0.0);
        let diffuse = lt.ambient + (1.0 - lt.ambient) * lambert * lit;
        let base = obj.color.mul_elem(lt.color);
        match obj.material {
            Material::Rubber => base * diffuse + lt.color * (0.08 * spec_angle.powi(8) * lit),
            Material::Metal => {
                let mut c = base * (0.55 * diffuse) + lt.color * (0.9 * spec_angle.powi(60) * lit);
                if depth > 0 {
                    let r = d - n * (2.0 * d.dot(n));
                    let reflected = self.shade(p_off, r.normalized(), depth - 1);
                    c = c + reflected.mul_elem(obj.color) * 0.45;
                }
                c
            }
        }
    }
}

/// A rendered view: RGB8 image and instance mask, both row-major with row 0 at the top.
pub struct Render {
    pub image: Vec<u8>,
    pub mask: Vec<u8>,
}

fn to_srgb8(c: f64) -> u8 {
    // Display gamma so the stored images look like photographs of the scene.
    (c.clamp(0.0, 1.0).powf(1.0 / 2.2) * 255.0).round() as u8
}

/// Renders a view. `antialias = s` averages an `s × s` grid of samples per pixel; the
/// mask comes from the pixel-centre ray, so it labels what the centre of each pixel shows.
pub fn render(world: &World, camera: &Camera, width: u32, height: u32, antialias: u32) -> Render {
    let s = antialias.max(1);
    let n = width as usize * height as usize;
    let mut image = Vec::with_capacity(n * 3);
    let mut mask = Vec::with_capacity(n);
    let o = camera.position();
    for v in 0..height {
        for u in 0..width {
            let mut acc = Vec3::ZERO;
            for sy in 0..s {
                for sx in 0..s {
                    let x = u as f64 + (sx as f64 + 0.5) / s as f64;
                    let y = v as f64 + (sy as f64 + 0.5) / s as f64;
                    acc = acc + world.shade(o, camera.direction_at(x, y), 1);
                }
            }
            let c = acc * (1.0 / (s * s) as f64);
            image.extend([to_srgb8(c.x), to_srgb8(c.y), to_srgb8(c.z)]);
            mask.push(world.instance(o, camera.pixel_direction(u, v)));
        }
    }
    Render { image, mask }
}
