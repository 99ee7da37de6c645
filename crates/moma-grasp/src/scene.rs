//! A scene ready for planning or scoring: cloud, support plane, object pixels and components.

use moma_core::{Intrinsics, Mask, MetricDepth};
use serde::{Deserialize, Serialize};

use crate::cloud::{CloudConfig, OrganisedCloud, Vec3};
use crate::error::{GraspError, Result, positive};
use crate::objects::{MIN_TRIAL_COMPONENT_PX, components_8};
use crate::plane::{PlaneConfig, SupportPlane, fit_support_plane};

/// How a scene is built from a depth map.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SceneConfig {
    /// Normals and edges.
    pub cloud: CloudConfig,
    /// Support-plane fit.
    pub plane: PlaneConfig,
    /// Without a mask, a pixel belongs to an object when it stands more than this above the
    /// support plane, metres. Default 0.01 m (docs/method.md §8).
    pub min_object_height_m: f32,
    /// Without a mask, connected object regions smaller than this are specks (noise), not objects,
    /// pixels. Default 200 (the trial rule of docs/method.md §8). With a mask every masked pixel with
    /// valid depth is an object pixel.
    pub min_object_px: usize,
    /// Without a mask, keep object regions that touch the image border. Default `false`: they
    /// are dropped. Such a region is only partly seen (no collision check can see past the
    /// frame), and it is most often not an object at all: bin walls, or the band along the
    /// frame's edge where real sensors' depth curls away from the table plane (on the
    /// gqcnn-primesense frames 9–16 mm above it, flat, and every top suction grasp landed there).
    /// With a mask the mask decides.
    #[serde(default)]
    pub keep_border_objects: bool,
    /// Without a mask, a region that encloses an opening of at least this area (square metres,
    /// measured at its rim, over what is seen at least 2 cm beyond it) is a container's walls
    /// (a bin, a tote), not an object: it is dropped, with the objects inside it kept. Default
    /// 0.04 m² (20 × 20 cm: a mug's or a bowl's opening is smaller, the smallest totes are
    /// larger); `f32::INFINITY` keeps every such region.
    #[serde(default = "default_container_opening_m2")]
    pub container_opening_m2: f32,
}

fn default_container_opening_m2() -> f32 {
    0.04
}

impl SceneConfig {
    /// The defaults, keeping (or not) the regions that touch the image border and the walls of
    /// containers: what `moma grasp --keep-border-objects --keep-containers` and Python's
    /// `keep_border_objects=`, `keep_containers=` ask for.
    pub fn keeping(border_objects: bool, containers: bool) -> Self {
        let default = Self::default();
        Self {
            keep_border_objects: border_objects,
            container_opening_m2: if containers {
                f32::INFINITY
            } else {
                default.container_opening_m2
            },
            ..default
        }
    }
}

impl Default for SceneConfig {
    fn default() -> Self {
        Self {
            cloud: CloudConfig::default(),
            plane: PlaneConfig::default(),
            min_object_height_m: 0.01,
            min_object_px: MIN_TRIAL_COMPONENT_PX,
            keep_border_objects: false,
            container_opening_m2: default_container_opening_m2(),
        }
    }
}

/// One object region: an 8-connected component of the object pixels.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ObjectComponent {
    /// Label in [`Scene::label`] (1-based).
    pub label: u32,
    /// Pixels in the component.
    pub pixel_count: usize,
    /// Mean camera-frame point of the component, metres.
    pub centroid_m: [f32; 3],
}

/// Depth map turned into everything the planners and the scorer need.
///
/// The cloud's normals and edge flags are computed only in the bounding box of the object pixels
/// grown by [`CloudConfig::object_margin_px`]; elsewhere they are unknown / false.
#[derive(Debug, Clone)]
pub struct Scene {
    /// The organised cloud.
    pub cloud: OrganisedCloud,
    /// The support plane; `None` when none was found.
    pub plane: Option<SupportPlane>,
    labels: Vec<u32>,
    components: Vec<ObjectComponent>,
    masked: bool,
    border_regions_dropped: usize,
    container_regions_dropped: usize,
    touching_split_off: usize,
    floating_regions_dropped: usize,
}

/// Pixel bounding box `(u0, v0, width, height)`.
type Bbox = (usize, usize, usize, usize);

/// The area (square metres) of the opening that the pixels `member` (inside `bbox`, their
/// rim nearest the camera at `z_rim_m`) enclose: of what they cut off from the border of
/// `bbox` (their 4-connected holes), the pixels with depth at least [`OPENING_DEPTH_M`]
/// beyond the rim (a floor seen through the opening, whatever lies on it; not a hole in the
/// depth, nor a shallow dent), each of the area its ray cuts from the plane of the rim: the
/// support plane raised to the region's 98th-percentile height (`z² / (fx · fy · |up · r|)` for
/// the ray r = ((u − cx) / fx, (v − cy) / fy, 1) meeting that plane at depth z): the opening's
/// own size, whatever the walls' height, the camera's distance and its tilt (scaled at the
/// nearest rim's depth instead, a tote's 0.12 m² opening seen 20–30° from above measured
/// 0.039–0.05 m², and its walls were planned on). Without a plane, each pixel counts
/// `z_rim² / (fx · fy)`.
fn enclosed_area_m2(
    member: &dyn Fn(usize) -> bool,
    (bu0, bv0, bw, bh): Bbox,
    cloud: &OrganisedCloud,
    plane: Option<&SupportPlane>,
    z_rim_m: f32,
) -> f32 {
    let w = cloud.width;
    let at = |bu: usize, bv: usize| (bv0 + bv) * w + bu0 + bu;
    let outside = outside_of(member, (bu0, bv0, bw, bh), w);
    let floor = (0..bw * bh)
        .filter(|&k| !outside[k])
        .map(|k| at(k % bw, k / bw))
        .filter(|&i| {
            !member(i) && cloud.valid[i] && cloud.points[i].z >= z_rim_m + OPENING_DEPTH_M
        });
    let flat = z_rim_m * z_rim_m / (cloud.fx * cloud.fy);
    let Some(plane) = plane else {
        return floor.count() as f32 * flat;
    };
    let Some((rim_m, _)) = rim_height_m(
        &|i| member(i) && cloud.valid[i],
        (bu0, bv0, bw, bh),
        cloud,
        plane,
    ) else {
        return 0.0;
    };
    let up = plane.up();
    floor
        .map(|i| {
            let (u, v) = ((i % w) as f32, (i / w) as f32);
            let r = Vec3::new((u - cloud.cx) / cloud.fx, (v - cloud.cy) / cloud.fy, 1.0);
            let along = up.dot(&r); // < 0 for a ray towards the plane below the camera
            let z = (rim_m - plane.offset_m) / along;
            if along < -1e-3 && z > 0.0 {
                z * z / (cloud.fx * cloud.fy * -along)
            } else {
                flat
            }
        })
        .sum()
}

/// The height (metres above `plane`) of the rim of the pixels `member` inside `bbox`: their
/// 98th-percentile height (a few flying pixels above it aside), and how many they are; `None`
/// without any. One rim for the opening's plane ([`enclosed_area_m2`]) and the objects
/// touching the walls ([`touching_objects`]).
fn rim_height_m(
    member: &dyn Fn(usize) -> bool,
    (bu0, bv0, bw, bh): Bbox,
    cloud: &OrganisedCloud,
    plane: &SupportPlane,
) -> Option<(f32, usize)> {
    let w = cloud.width;
    let mut heights: Vec<f32> = (0..bw * bh)
        .map(|k| (bv0 + k / bw) * w + bu0 + k % bw)
        .filter(|&i| member(i))
        .map(|i| plane.height_m(&cloud.points[i]))
        .collect();
    let n = heights.len();
    let k = n.checked_sub(1)? * 98 / 100;
    Some((*heights.select_nth_unstable_by(k, f32::total_cmp).1, n))
}

/// The 4-neighbours (row-major indices) of pixel `k` of a `w × h` image.
fn neighbours_4(k: usize, w: usize, h: usize) -> impl Iterator<Item = usize> {
    let (u, v) = (k % w, k / w);
    [
        (u > 0).then(|| k - 1),
        (u + 1 < w).then_some(k + 1),
        (v > 0).then(|| k - w),
        (v + 1 < h).then_some(k + w),
    ]
    .into_iter()
    .flatten()
}

/// The pixels of `bbox` (in its own row-major order) that the pixels `member` do not cut off
/// from its border: a flood fill of the non-member pixels from the border, 4-connected. What
/// it leaves out that is no member is what `member` encloses.
fn outside_of(member: &dyn Fn(usize) -> bool, (bu0, bv0, bw, bh): Bbox, w: usize) -> Vec<bool> {
    let at = |k: usize| (bv0 + k / bw) * w + bu0 + k % bw;
    let mut outside = vec![false; bw * bh];
    let mut stack = Vec::new();
    for bv in 0..bh {
        for bu in 0..bw {
            let k = bv * bw + bu;
            let border = bu == 0 || bv == 0 || bu + 1 == bw || bv + 1 == bh;
            if border && !member(at(k)) && !outside[k] {
                outside[k] = true;
                stack.push(k);
            }
        }
    }
    while let Some(k) = stack.pop() {
        for n in neighbours_4(k, bw, bh) {
            if !outside[n] && !member(at(n)) {
                outside[n] = true;
                stack.push(n);
            }
        }
    }
    outside
}

/// How far beyond a container's rim (metres, along the camera's z) the floor seen through its
/// opening lies at least ([`enclosed_area_m2`]).
const OPENING_DEPTH_M: f32 = 0.02;

/// The bounding boxes and nearest depths (metres) of the `n` pixel sets `of(i)` (1-based; 0 =
/// none) of the cloud's image.
fn boxes(cloud: &OrganisedCloud, n: usize, of: &dyn Fn(usize) -> usize) -> Vec<(Bbox, f32)> {
    let w = cloud.width;
    let mut b = vec![(usize::MAX, usize::MAX, 0, 0, f32::INFINITY); n + 1];
    for i in 0..cloud.valid.len() {
        let l = of(i);
        if l == 0 {
            continue;
        }
        let (u, v) = (i % w, i / w);
        let e = &mut b[l];
        (e.0, e.1, e.2, e.3) = (e.0.min(u), e.1.min(v), e.2.max(u), e.3.max(v));
        if cloud.valid[i] {
            e.4 = e.4.min(cloud.points[i].z);
        }
    }
    b.into_iter()
        .map(|(u0, v0, u1, v1, z)| {
            let bbox = if u0 == usize::MAX {
                (0, 0, 0, 0)
            } else {
                (u0, v0, u1 - u0 + 1, v1 - v0 + 1)
            };
            (bbox, z)
        })
        .collect()
}

/// Whether pixels in `bbox`, nearest at `z_near_m`, could enclose `opening_m2` at all: a
/// loose bound of [`enclosed_area_m2`] (its rim plane may lie up to twice as far as the
/// nearest pixel and be seen at up to 60° from its normal: a factor of 8), only to skip the
/// flood fills of regions far too small.
fn could_enclose(
    (_, _, bw, bh): Bbox,
    z_near_m: f32,
    cloud: &OrganisedCloud,
    opening_m2: f32,
) -> bool {
    bw >= 3
        && bh >= 3
        && z_near_m.is_finite()
        && 8.0 * (bw * bh) as f32 * z_near_m * z_near_m / (cloud.fx * cloud.fy) >= opening_m2
}

/// Removes the walls of containers from the objects ([`SceneConfig::container_opening_m2`]):
/// every region (`labels`, `counts` from [`components_8`] of `object`) that encloses an
/// opening of at least `opening_m2` square metres ([`enclosed_area_m2`]: the floor and
/// whatever lies on it) leaves the objects; what lies inside it stays. An object touching a
/// wall is part of the wall's region: it is split off ([`touching_objects`]) where its top
/// lies below the rim, and stays an object under a new label (pushed onto `counts`). Returns
/// how many regions of at least `min_px` pixels were dropped, and how many objects were split
/// off them.
///
/// Written here, not taken from a crate: flood fills of the complement of one labelled region
/// within its bounding box (imageproc fills the holes of a binary image, not those of one
/// labelled region among others).
fn drop_container_walls(
    object: &mut [bool],
    labels: &mut [u32],
    counts: &mut Vec<usize>,
    cloud: &OrganisedCloud,
    plane: Option<&SupportPlane>,
    opening_m2: f32,
    min_px: usize,
) -> (usize, usize) {
    if !opening_m2.is_finite() || cloud.width < 3 || cloud.height < 3 || counts.is_empty() {
        return (0, 0);
    }
    let n = counts.len();
    let regions = {
        let labels = &*labels;
        boxes(cloud, n, &|i| labels[i] as usize)
    };
    let mut walls = vec![false; n + 1];
    for l in 1..=n {
        let (bbox, z_near) = regions[l];
        if counts[l - 1] < min_px || !could_enclose(bbox, z_near, cloud, opening_m2) {
            continue;
        }
        let lu = l as u32;
        let labels = &*labels;
        walls[l] = enclosed_area_m2(&|i| labels[i] == lu, bbox, cloud, plane, z_near) >= opening_m2;
    }
    // the objects touching a wall, found before the wall's pixels leave
    let touching: Vec<Vec<usize>> = match plane {
        Some(plane) => (1..=n)
            .filter(|&l| walls[l])
            .flat_map(|l| touching_objects(labels, l as u32, regions[l].0, cloud, plane, min_px))
            .collect(),
        None => Vec::new(),
    };
    let dropped = drop_regions(object, labels, counts, &walls, min_px);
    for pixels in &touching {
        counts.push(pixels.len());
        let label = counts.len() as u32;
        for &i in pixels {
            object[i] = true;
            labels[i] = label;
        }
    }
    (dropped, touching.len())
}

/// The objects touching a container's walls, as pixel lists. Within the wall's region `l`
/// (bounding box `bbox`), heights above the support plane are smoothed over
/// [`TOUCHING_SMOOTH_M`] (the region's own pixels only); a pixel at least [`RIM_BAND_M`] below
/// the rim (the region's 98th-percentile height) whose smoothed height changes by less than
/// [`TOUCHING_MAX_SLOPE`] times the distance along the plane to its neighbours
/// [`TOUCHING_SLOPE_BASE_M`] away along the image's rows and columns is part of an object's
/// flat top. Each 8-connected group of them that holds a square of [`TOUCHING_MIN_WIDTH_M`]
/// (a wall's own lower top, a handle's cut-out, is a narrower strip) is grown back to the top's
/// edges over the region's pixels at the group's own smoothed height (within
/// [`TOUCHING_TOP_BAND_M`]: never up or down a wall's face), and is an object when it has at
/// least `min_px` pixels. The walls' faces are steep and their rim lies at the rim's height:
/// neither is an object. An object as tall as the rim stays with the walls; one whose top is
/// not flat (a ball) as well.
fn touching_objects(
    labels: &[u32],
    l: u32,
    (bu0, bv0, bw, bh): Bbox,
    cloud: &OrganisedCloud,
    plane: &SupportPlane,
    min_px: usize,
) -> Vec<Vec<usize>> {
    let w = cloud.width;
    let at = |bu: usize, bv: usize| (bv0 + bv) * w + bu0 + bu;
    let member = |i: usize| labels[i] == l && cloud.valid[i];
    let height = |i: usize| plane.height_m(&cloud.points[i]);
    let rim_m = match rim_height_m(&member, (bu0, bv0, bw, bh), cloud, plane) {
        Some((rim_m, n)) if n >= min_px => rim_m,
        _ => return Vec::new(),
    };
    let below_rim = |i: usize| member(i) && height(i) < rim_m - RIM_BAND_M;
    let up = plane.up();
    // the region's height smoothed over a window of TOUCHING_SMOOTH_M (its own pixels only,
    // summed-area tables): the depth's noise would tilt a flat top at the slope's base
    let z_mid = {
        let mut z: Vec<f32> = (0..bw * bh)
            .map(|k| at(k % bw, k / bw))
            .filter(|&i| member(i))
            .map(|i| cloud.points[i].z)
            .collect();
        let k = z.len() / 2;
        *z.select_nth_unstable_by(k, f32::total_cmp).1
    };
    let px_of = |metres: f32| ((metres * cloud.fx / z_mid).round() as usize).max(1);
    let smoothed = box_mean(
        &(0..bw * bh)
            .map(|k| {
                let i = at(k % bw, k / bw);
                member(i).then(|| height(i))
            })
            .collect::<Vec<_>>(),
        bw,
        bh,
        px_of(TOUCHING_SMOOTH_M) / 2,
    );
    // the slope between pixels k and j of the box: smoothed height change over the distance
    // along the plane
    let slope = |k: usize, j: usize| {
        let d = cloud.points[at(j % bw, j / bw)] - cloud.points[at(k % bw, k / bw)];
        let along = up.dot(&d);
        let lateral = (d.norm_squared() - along * along).max(0.0).sqrt();
        let dh = (smoothed[j] - smoothed[k]).abs();
        if lateral > 0.0 {
            dh / lateral
        } else {
            f32::INFINITY
        }
    };
    let s = px_of(TOUCHING_SLOPE_BASE_M);
    let mut top = vec![false; bw * bh];
    for bv in 0..bh {
        for bu in 0..bw {
            let k = bv * bw + bu;
            if !below_rim(at(bu, bv)) || smoothed[k].is_nan() {
                continue;
            }
            let mut flat = true;
            let mut seen = false;
            for (nu, nv) in [
                (bu.checked_sub(s), Some(bv)),
                (Some(bu + s).filter(|&x| x < bw), Some(bv)),
                (Some(bu), bv.checked_sub(s)),
                (Some(bu), Some(bv + s).filter(|&y| y < bh)),
            ] {
                if let (Some(nu), Some(nv)) = (nu, nv) {
                    let j = nv * bw + nu;
                    if member(at(nu, nv)) && !smoothed[j].is_nan() {
                        seen = true;
                        flat &= slope(k, j) < TOUCHING_MAX_SLOPE;
                    }
                }
            }
            top[k] = flat && seen;
        }
    }
    let base_px = s + px_of(TOUCHING_SMOOTH_M) / 2;
    let (seeds, counts) = components_8(&top, moma_core::ImageSize::new(bw, bh));
    // each group's box (in the region's box), so that the work below stays within it
    let mut group_box = vec![(usize::MAX, usize::MAX, 0usize, 0usize); counts.len()];
    for (k, &g) in seeds.iter().enumerate().filter(|(_, g)| **g > 0) {
        let (bu, bv) = (k % bw, k / bw);
        let b = &mut group_box[g as usize - 1];
        *b = (b.0.min(bu), b.1.min(bv), b.2.max(bu), b.3.max(bv));
    }
    // what the wall region encloses (its opening: the floor and whatever lies on it) and what
    // lies outside it: down the sides of an object touching the walls from inside is the
    // opening only; down a wall's own lower top (a handle's cut-out), a ledge or a rib, the
    // outside as well
    let outside = outside_of(&member, (bu0, bv0, bw, bh), w);
    // the side (pixels) of the square an object's top must hold, at the region's median depth
    let side_px = px_of(TOUCHING_MIN_WIDTH_M);
    // pixels an object took: no other grows into them
    let mut claimed = vec![false; bw * bh];
    let mut objects = Vec::new();
    // a group smaller than the square cannot hold it (most of the specks a noisy depth leaves)
    for (g, _) in counts
        .iter()
        .enumerate()
        .filter(|(_, c)| **c >= side_px * side_px)
    {
        let label = g as u32 + 1;
        // the group's box grown by what the top may regain, clipped to the region's box
        let (u0, v0, u1, v1) = group_box[g];
        let (u0, v0) = (u0.saturating_sub(base_px), v0.saturating_sub(base_px));
        let (u1, v1) = ((u1 + base_px + 1).min(bw), (v1 + base_px + 1).min(bh));
        let (gw, gh) = (u1 - u0, v1 - v0);
        // pixel q of the group's window as a pixel of the region's box
        let k_of = |q: usize| (v0 + q / gw) * bw + u0 + q % gw;
        let local: Vec<bool> = (0..gw * gh).map(|q| seeds[k_of(q)] == label).collect();
        if !holds_square(&local, gw, gh, side_px) {
            continue; // a strip: the top of a wall's lower part (a handle's cut-out), no object
        }
        // grow the top back to its edges (the smoothing and the slope's base shrank it by
        // base_px): over the region's pixels at the top's own (smoothed) height, never up or
        // down a face, nor into another object's top
        let mut inside = local;
        let mut front: Vec<usize> = (0..gw * gh).filter(|&q| inside[q]).collect();
        let mut top_m: Vec<f32> = front.iter().map(|&q| smoothed[k_of(q)]).collect();
        let (lo, hi) = {
            let n = top_m.len() - 1;
            let lo = *top_m.select_nth_unstable_by(n / 50, f32::total_cmp).1;
            let hi = *top_m.select_nth_unstable_by(n - n / 50, f32::total_cmp).1;
            (lo - TOUCHING_TOP_BAND_M, hi + TOUCHING_TOP_BAND_M)
        };
        let on_top = |k: usize| {
            seeds[k] == 0
                && !claimed[k]
                && below_rim(at(k % bw, k / bw))
                && (lo..=hi).contains(&smoothed[k])
        };
        for _ in 0..base_px {
            let mut next = Vec::new();
            for q in front {
                for n in neighbours_4(q, gw, gh) {
                    if !inside[n] && on_top(k_of(n)) {
                        inside[n] = true;
                        next.push(n);
                    }
                }
            }
            front = next;
        }
        let ks: Vec<usize> = (0..gw * gh).filter(|&q| inside[q]).map(k_of).collect();
        if ks.len() < min_px
            || !descends_into_opening_only(
                &ks,
                hi,
                &outside,
                &member,
                &height,
                (bu0, bv0, bw, bh),
                w,
            )
        {
            continue;
        }
        for &k in &ks {
            claimed[k] = true;
        }
        objects.push(ks.iter().map(|&k| at(k % bw, k / bw)).collect());
    }
    objects
}

/// Whether the region's pixels reached from the top `ks` (indices in the region's box `bbox`)
/// by never climbing above `top_m` (the top's own highest level: the top itself, its sides and
/// the walls' faces beside them, down to wherever they end; the rim lies at least
/// [`RIM_BAND_M`] higher) border the opening the region encloses and never its outside
/// (`outside`, from [`outside_of`]): an object standing inside the container. A wall's own
/// lower top, a ledge or a rib on its outside reach both, or the outside alone.
fn descends_into_opening_only(
    ks: &[usize],
    top_m: f32,
    outside: &[bool],
    member: &dyn Fn(usize) -> bool,
    height: &dyn Fn(usize) -> f32,
    (bu0, bv0, bw, bh): Bbox,
    w: usize,
) -> bool {
    let at = |k: usize| (bv0 + k / bw) * w + bu0 + k % bw;
    let mut seen = vec![false; bw * bh];
    let mut stack: Vec<usize> = ks.to_vec();
    for &k in ks {
        seen[k] = true;
    }
    let mut opening = false;
    while let Some(k) = stack.pop() {
        for n in neighbours_4(k, bw, bh) {
            if seen[n] {
                continue;
            }
            seen[n] = true;
            if !member(at(n)) {
                if outside[n] {
                    return false;
                }
                opening = true;
            } else if height(at(n)) <= top_m {
                stack.push(n);
            }
        }
    }
    opening
}

/// Whether the pixels set in the `bw × bh` mask `inside` hold a whole `side × side` square (a
/// summed-area table of them).
fn holds_square(inside: &[bool], bw: usize, bh: usize, side: usize) -> bool {
    if side > bw || side > bh {
        return false;
    }
    let mut sat = vec![0u32; (bw + 1) * (bh + 1)];
    for v in 0..bh {
        let mut row = 0u32;
        for u in 0..bw {
            row += u32::from(inside[v * bw + u]);
            sat[(v + 1) * (bw + 1) + u + 1] = sat[v * (bw + 1) + u + 1] + row;
        }
    }
    let full = (side * side) as u32;
    (side..=bh).any(|v1| {
        (side..=bw).any(|u1| {
            let (u0, v0) = (u1 - side, v1 - side);
            sat[v1 * (bw + 1) + u1] + sat[v0 * (bw + 1) + u0]
                - sat[v0 * (bw + 1) + u1]
                - sat[v1 * (bw + 1) + u0]
                == full
        })
    })
}

/// How far (metres, along the support plane's normal) beyond its flat part's 2nd and 98th
/// percentile heights the top of an object touching a container's walls is grown back to
/// its edges ([`touching_objects`]).
const TOUCHING_TOP_BAND_M: f32 = 0.003;

/// The narrowest top (metres, a square's side at the wall region's median depth) of an object
/// that [`touching_objects`] splits off a container's walls: a wall's own top where it is
/// lower (a handle's cut-out) is a strip narrower than this, a box's or a bottle's top is not.
const TOUCHING_MIN_WIDTH_M: f32 = 0.015;

/// How far below a container's rim (metres, along the support plane's normal) an object
/// touching its walls must stand to be split off ([`touching_objects`]): the rim's own
/// pixels, and those of a lip or a rounded edge, lie within it.
const RIM_BAND_M: f32 = 0.015;

/// The distance (metres, at the wall region's median depth, along the image's rows and
/// columns) over which [`touching_objects`] measures a slope: long enough that the depth's
/// noise barely tilts a flat top, short enough for a small object's top.
const TOUCHING_SLOPE_BASE_M: f32 = 0.005;

/// The window (metres, a square's side at the wall region's median depth) over which
/// [`touching_objects`] smooths the heights before measuring slopes: a depth model's noise of
/// 0.5 % of the depth, correlated over a few pixels, tilts a 1 cm base by up to 0.5 unsmoothed.
const TOUCHING_SMOOTH_M: f32 = 0.008;

/// The mean of the `Some` values of a `w × h` image over a `(2r + 1)²` window around each
/// pixel (NaN at `None` pixels and where the window holds none): summed-area tables.
fn box_mean(values: &[Option<f32>], w: usize, h: usize, r: usize) -> Vec<f32> {
    let (sw, sh) = (w + 1, h + 1);
    let mut sum = vec![0.0f64; sw * sh];
    let mut cnt = vec![0u32; sw * sh];
    for v in 0..h {
        let (mut rs, mut rc) = (0.0f64, 0u32);
        for u in 0..w {
            if let Some(x) = values[v * w + u] {
                rs += f64::from(x);
                rc += 1;
            }
            sum[(v + 1) * sw + u + 1] = sum[v * sw + u + 1] + rs;
            cnt[(v + 1) * sw + u + 1] = cnt[v * sw + u + 1] + rc;
        }
    }
    (0..w * h)
        .map(|k| {
            let (u, v) = (k % w, k / w);
            if values[k].is_none() {
                return f32::NAN;
            }
            let (u0, v0, u1, v1) = (
                u.saturating_sub(r),
                v.saturating_sub(r),
                (u + r + 1).min(w),
                (v + r + 1).min(h),
            );
            let at = |t: &[f64], uu: usize, vv: usize| t[vv * sw + uu];
            let s = at(&sum, u1, v1) + at(&sum, u0, v0) - at(&sum, u1, v0) - at(&sum, u0, v1);
            let c = cnt[v1 * sw + u1] + cnt[v0 * sw + u0] - cnt[v0 * sw + u1] - cnt[v1 * sw + u0];
            if c == 0 {
                f32::NAN
            } else {
                (s / f64::from(c)) as f32
            }
        })
        .collect()
}

/// The steepest slope (height over distance along the support plane) of an object's top in
/// [`touching_objects`]: 45°. A wall's faces, seen from above at any angle, are far steeper.
const TOUCHING_MAX_SLOPE: f32 = 1.0;

/// Removes the regions `drop[label]` (`labels`, `counts` from [`components_8`] of `object`):
/// their pixels leave `object` and get label 0, their counts become 0. Returns how many of them
/// had at least `min_px` pixels (would have been objects).
fn drop_regions(
    object: &mut [bool],
    labels: &mut [u32],
    counts: &mut [usize],
    drop: &[bool],
    min_px: usize,
) -> usize {
    for (o, l) in object.iter_mut().zip(labels.iter_mut()) {
        if drop[*l as usize] {
            *o = false;
            *l = 0;
        }
    }
    let mut dropped = 0;
    for (c, _) in counts.iter_mut().zip(&drop[1..]).filter(|(_, t)| **t) {
        dropped += usize::from(*c >= min_px);
        *c = 0;
    }
    dropped
}

/// Removes every 8-connected region (`labels`, `counts` from [`components_8`] of `object`) with
/// a pixel on the image border: its pixels leave `object` and get label 0, its count becomes 0.
/// Returns how many of them had at least `min_px` pixels (would have been objects).
fn drop_border_regions(
    object: &mut [bool],
    labels: &mut [u32],
    counts: &mut [usize],
    size: moma_core::ImageSize,
    min_px: usize,
) -> usize {
    let (w, h) = (size.width, size.height);
    if w == 0 || h == 0 {
        return 0;
    }
    let mut touches = vec![false; counts.len() + 1];
    let border = (0..w)
        .flat_map(|u| [u, (h - 1) * w + u])
        .chain((0..h).flat_map(|v| [v * w, v * w + w - 1]));
    for i in border {
        touches[labels[i] as usize] = true;
    }
    touches[0] = false;
    drop_regions(object, labels, counts, &touches, min_px)
}

/// Removes every region (`labels`, `counts` of `object`) with no pixel beside a support: none
/// of its 4-neighbours outside it has valid depth within `2 · min_height_m` of the support
/// plane or belongs to a container dropped as one (`container`: a tote's floor may stand above
/// the table's plane). Such a region does not stand on the table or in the tote the cell looks
/// at (a monitor arm or a shelf in the background, seen against a far wall or beside no depth),
/// and grasps planned on it are no cell's. Returns how many of them had at least `min_px`
/// pixels.
#[allow(clippy::too_many_arguments)] // the scene's parts, each a different thing
fn drop_floating_regions(
    object: &mut [bool],
    labels: &mut [u32],
    counts: &mut [usize],
    cloud: &OrganisedCloud,
    plane: &SupportPlane,
    container: &[bool],
    min_height_m: f32,
    min_px: usize,
) -> usize {
    let (w, h) = (cloud.width, cloud.height);
    let mut beside = vec![false; counts.len() + 1];
    let support = |j: usize| {
        cloud.valid[j]
            && labels[j] == 0
            && (container[j] || plane.height_m(&cloud.points[j]).abs() <= 2.0 * min_height_m)
    };
    for (i, &label) in labels.iter().enumerate() {
        let l = label as usize;
        if l != 0 && !beside[l] && neighbours_4(i, w, h).any(support) {
            beside[l] = true;
        }
    }
    let drop: Vec<bool> = beside
        .iter()
        .enumerate()
        .map(|(l, b)| l > 0 && !b && counts.get(l - 1).is_some_and(|&c| c > 0))
        .collect();
    drop_regions(object, labels, counts, &drop, min_px)
}

impl Scene {
    /// Builds the scene. With `mask`, objects are the masked pixels with valid depth and the plane
    /// is fitted outside the mask (on all valid pixels when fewer than 3 lie outside); without, the
    /// plane is fitted on all valid pixels and objects are regions more than
    /// `min_object_height_m` above it with at least `min_object_px` pixels that do not touch the
    /// image border (unless `keep_border_objects`), do not enclose an opening of
    /// `container_opening_m2` (a container's walls) and lie beside the support plane or a
    /// container somewhere (else they are background: [`Self::floating_note`]).
    ///
    /// # Errors
    /// Invalid intrinsics/config, intrinsics or mask of another size than `depth`, all-invalid
    /// depth, a mask whose pixels all lack depth.
    pub fn build(
        depth: &MetricDepth,
        intrinsics: &Intrinsics,
        mask: Option<&Mask>,
        config: &SceneConfig,
    ) -> Result<Self> {
        positive(
            "min_object_height_m",
            config.min_object_height_m,
            GraspError::InvalidConfig,
        )?;
        if let Some(m) = mask
            && m.size() != depth.size()
        {
            return Err(GraspError::SizeMismatch {
                what: "mask",
                expected: depth.size(),
                got: m.size(),
            });
        }
        intrinsics.validate().map_err(GraspError::Intrinsics)?;
        if intrinsics.size() != depth.size() {
            return Err(GraspError::SizeMismatch {
                what: "camera intrinsics",
                expected: depth.size(),
                got: intrinsics.size(),
            });
        }
        let mut cloud = OrganisedCloud::build(depth, intrinsics, &config.cloud, false)?;
        let size = depth.size();
        let masked: Option<Vec<bool>> = mask.map(|m| m.data().iter().copied().collect());
        let plane = match &masked {
            Some(m) => {
                let masked_px = m.iter().filter(|&&b| b).count();
                let object_px = (0..m.len()).filter(|&i| m[i] && cloud.valid[i]).count();
                if object_px == 0 {
                    return Err(GraspError::MaskNoValidDepth { masked_px });
                }
                let outside: Vec<bool> = m.iter().map(|b| !b).collect();
                let n_out = (0..m.len())
                    .filter(|&i| outside[i] && cloud.valid[i])
                    .count();
                let region = (n_out >= 3).then_some(outside.as_slice());
                fit_support_plane(&cloud, region, &config.plane)?
            }
            None => fit_support_plane(&cloud, None, &config.plane)?,
        };
        let mut object: Vec<bool> = match (&masked, &plane) {
            (Some(m), _) => (0..m.len()).map(|i| m[i] && cloud.valid[i]).collect(),
            (None, Some(p)) => (0..cloud.valid.len())
                .map(|i| {
                    cloud.valid[i] && p.height_m(&cloud.points[i]) > config.min_object_height_m
                })
                .collect(),
            (None, None) => vec![false; cloud.valid.len()],
        };
        // One labelling serves the border rule and the components below.
        let (mut labels, mut counts) = components_8(&object, size);
        let border_regions_dropped = if masked.is_none() && !config.keep_border_objects {
            drop_border_regions(
                &mut object,
                &mut labels,
                &mut counts,
                size,
                config.min_object_px,
            )
        } else {
            0
        };
        let before_containers = object.clone();
        let (container_regions_dropped, touching_split_off) = if masked.is_none() {
            drop_container_walls(
                &mut object,
                &mut labels,
                &mut counts,
                &cloud,
                plane.as_ref(),
                config.container_opening_m2,
                config.min_object_px,
            )
        } else {
            (0, 0)
        };
        let floating_regions_dropped = match (&masked, &plane) {
            (None, Some(p)) => {
                let container: Vec<bool> = before_containers
                    .iter()
                    .zip(&object)
                    .map(|(&was, &is)| was && !is)
                    .collect();
                drop_floating_regions(
                    &mut object,
                    &mut labels,
                    &mut counts,
                    &cloud,
                    p,
                    &container,
                    config.min_object_height_m,
                    config.min_object_px,
                )
            }
            _ => 0,
        };
        // Normals and edges only around the objects (the planners and the scorer query no other).
        let (w, h) = (size.width, size.height);
        let (mut u0, mut u1, mut v0, mut v1) = (usize::MAX, 0, usize::MAX, 0);
        for (i, _) in object.iter().enumerate().filter(|(_, b)| **b) {
            let (u, v) = (i % w, i / w);
            u0 = u0.min(u);
            u1 = u1.max(u);
            v0 = v0.min(v);
            v1 = v1.max(v);
        }
        if u0 != usize::MAX {
            let m = config.cloud.object_margin_px;
            cloud.compute_normals(
                u0.saturating_sub(m),
                (u1 + m + 1).min(w),
                v0.saturating_sub(m),
                (v1 + m + 1).min(h),
                &config.cloud,
            );
        }
        let min_px = if masked.is_some() {
            1
        } else {
            config.min_object_px
        };
        // Relabel so that kept components are 1..=k.
        let mut remap = vec![0u32; counts.len() + 1];
        let mut sums = Vec::new();
        for (k, &c) in counts.iter().enumerate() {
            // c = 0: a region the border rule dropped (components_8 counts are at least 1)
            if c > 0 && c >= min_px {
                sums.push((Vec3::zeros(), 0usize));
                remap[k + 1] = sums.len() as u32;
            }
        }
        for (i, l) in labels.iter_mut().enumerate() {
            *l = remap[*l as usize];
            if *l > 0 {
                let s = &mut sums[*l as usize - 1];
                s.0 += cloud.points[i];
                s.1 += 1;
            }
        }
        let components = sums
            .iter()
            .enumerate()
            .map(|(k, (sum, n))| {
                let c = sum / *n as f32;
                ObjectComponent {
                    label: k as u32 + 1,
                    pixel_count: *n,
                    centroid_m: [c.x, c.y, c.z],
                }
            })
            .collect();
        Ok(Self {
            cloud,
            plane,
            labels,
            components,
            masked: mask.is_some(),
            border_regions_dropped,
            container_regions_dropped,
            touching_split_off,
            floating_regions_dropped,
        })
    }

    /// The scene of another depth of the same view inside a region of interest: `depth_roi`
    /// holds the depth of the pixels `roi` (`roi.height × roi.width`, e.g. a depth map drawn
    /// from an error model), `intrinsics_roi` the camera with its principal point moved to the
    /// region. The support plane and the object labels are this scene's (the camera frame is
    /// the same); the cloud, normals and silhouette edges are the new depth's. Much cheaper than
    /// [`Scene::build`] for many draws of one frame.
    ///
    /// # Errors
    /// A region outside this scene, sizes that disagree, invalid intrinsics, an all-invalid
    /// depth.
    pub fn with_depth_in(
        &self,
        roi: moma_core::error_model::Roi,
        depth_roi: &MetricDepth,
        intrinsics_roi: &Intrinsics,
        config: &SceneConfig,
    ) -> Result<Self> {
        let (w, h) = (self.cloud.width, self.cloud.height);
        if roi.u0 + roi.width > w || roi.v0 + roi.height > h {
            return Err(GraspError::InvalidConfig(format!(
                "region {}×{} at ({}, {}) lies outside the {w}×{h} scene",
                roi.width, roi.height, roi.u0, roi.v0
            )));
        }
        let mut cloud = OrganisedCloud::build(depth_roi, intrinsics_roi, &config.cloud, false)?;
        cloud.compute_normals(0, roi.width, 0, roi.height, &config.cloud);
        let labels = (0..roi.height)
            .flat_map(|v| {
                let row = (roi.v0 + v) * w + roi.u0;
                self.labels[row..row + roi.width].iter().copied()
            })
            .collect();
        Ok(Self {
            cloud,
            plane: self.plane,
            labels,
            components: self.components.clone(),
            masked: self.masked,
            border_regions_dropped: 0,
            container_regions_dropped: 0,
            touching_split_off: 0,
            floating_regions_dropped: 0,
        })
    }

    /// Object label of pixel `index` (0 = not an object).
    #[inline]
    pub fn label(&self, index: usize) -> u32 {
        self.labels[index]
    }

    /// Whether pixel `index` belongs to an object.
    #[inline]
    pub fn is_object(&self, index: usize) -> bool {
        self.labels[index] != 0
    }

    /// The object components (label `k` is `components()[k - 1]`).
    pub fn components(&self) -> &[ObjectComponent] {
        &self.components
    }

    /// Median depth of the object pixels (every 4th one), metres; the median of all valid pixels
    /// when there is no object pixel.
    pub fn object_depth_m(&self) -> f32 {
        let c = &self.cloud;
        let depths = |objects_only: bool| -> Vec<f32> {
            (0..c.valid.len())
                .step_by(4)
                .filter(|&i| c.valid[i] && (!objects_only || self.is_object(i)))
                .map(|i| c.points[i].z)
                .collect()
        };
        let mut z = depths(true);
        if z.is_empty() {
            z = depths(false);
        }
        if z.is_empty() {
            return 0.0;
        }
        let k = z.len() / 2;
        *z.select_nth_unstable_by(k, f32::total_cmp).1
    }

    /// Whether objects came from a mask.
    pub fn is_masked(&self) -> bool {
        self.masked
    }

    /// Regions of at least [`SceneConfig::min_object_px`] pixels above the support plane that
    /// were not made objects because they touch the image border (0 with a mask or with
    /// [`SceneConfig::keep_border_objects`]).
    pub fn border_regions_dropped(&self) -> usize {
        self.border_regions_dropped
    }

    /// Regions of at least [`SceneConfig::min_object_px`] pixels above the support plane that
    /// were not made objects because they enclose an opening of a container's size
    /// ([`SceneConfig::container_opening_m2`]; 0 with a mask).
    pub fn container_regions_dropped(&self) -> usize {
        self.container_regions_dropped
    }

    /// What a user should know of the regions dropped for touching the image border
    /// ([`Self::border_regions_dropped`]): `None` when there were none. One text for `moma
    /// grasp` and Python's `plan_grasps`, each adding its own way to keep them.
    pub fn border_note(&self) -> Option<String> {
        (self.border_regions_dropped > 0).then(|| {
            format!(
                "{} region(s) above the support plane touch the image border and are not \
                 planned on (partly seen)",
                self.border_regions_dropped
            )
        })
    }

    /// Regions of at least [`SceneConfig::min_object_px`] pixels above the support plane that
    /// were not made objects because no pixel of theirs lies beside a support (0 with a mask):
    /// background things seen against a far wall or beside no depth.
    pub fn floating_regions_dropped(&self) -> usize {
        self.floating_regions_dropped
    }

    /// What a user should know of the regions dropped for standing on no support
    /// ([`Self::floating_regions_dropped`]): `None` when there were none.
    pub fn floating_note(&self) -> Option<String> {
        (self.floating_regions_dropped > 0).then(|| {
            format!(
                "{} region(s) above the support plane lie beside neither it nor a container \
                 (background: seen against a far wall or beside no depth) and are not planned on",
                self.floating_regions_dropped
            )
        })
    }

    /// Every note of the regions left out ([`Self::border_note`], [`Self::container_note`],
    /// [`Self::floating_note`]) under its key (`border_note`, `container_note`,
    /// `floating_note`): what the grasp check lists and the ROS 2 node's diagnostics carry.
    pub fn notes(&self) -> Vec<(&'static str, String)> {
        [
            ("border_note", self.border_note()),
            ("container_note", self.container_note()),
            ("floating_note", self.floating_note()),
        ]
        .into_iter()
        .filter_map(|(key, note)| note.map(|n| (key, n)))
        .collect()
    }

    /// What a user should know of the container walls dropped ([`Self::container_regions_dropped`]):
    /// `None` when there were none.
    pub fn container_note(&self) -> Option<String> {
        (self.container_regions_dropped > 0).then(|| {
            format!(
                "{} region(s) above the support plane enclose an opening of a container's size \
                 (a bin's or a tote's walls) and are not planned on; objects inside it are, \
                 and so are objects touching its walls with a flat top at least {:.0} mm below \
                 its rim ({} split off; an object mask chooses objects)",
                self.container_regions_dropped,
                RIM_BAND_M * 1000.0,
                self.touching_split_off,
            )
        })
    }

    /// "Up": the support plane's normal, or the direction towards the camera (`-z`) without a
    /// plane.
    pub fn up(&self) -> Vec3 {
        self.plane.map_or(Vec3::new(0.0, 0.0, -1.0), |p| p.up())
    }

    /// Centroid of the component with `label` (metres); `None` for label 0.
    pub(crate) fn centroid(&self, label: u32) -> Option<Vec3> {
        (label > 0).then(|| Vec3::from(self.components[label as usize - 1].centroid_m))
    }
}
