"""Sort `perf script -F ip,sym --inline` samples by the innermost rebraid
frame that names a part of the traversal kernels (see profile-trace.sh)."""
import collections
import sys

# Checked innermost frame first; the first rule a frame matches wins.
RULES = [
    ("triangle tests (Triangle4 SSE, scalar fallback)",
     ["triangle4::", "intersect_triangle", "intersect_leaf", "occluded_leaf"]),
    ("box tests (8-wide slab test)",
     ["Avx2Tester as rebraid::bvh::simd::BoxTester", "SseTester as", "ScalarTester as", "hit_node"]),
    ("ray setup (testers, watertight shear, instance transform)",
     ["Avx2Tester::new", "SseTester::new", "WatertightRay::new", "BoxRay::new", "local_ray", "plane_order"]),
    ("top level: leaves and entry into object BVHs",
     ["toplevel::ObjectBvh::query_node", "RayWalk", "TopLevelAccel"]),
    ("traversal loop (stack, child order, leaf decode)", ["bvh::simd::traverse"]),
]
# Frames that mark a sample as tracing (the unwinder may stop before the
# batch entry point) or as something else (building, ray generation).
TRACING = ["intersect_batch", "occluded_batch", "par_query", "bvh::simd::", "triangle4::",
           "query_node", "RayWalk", "TopLevelAccel::", "FlatAccel::", "Scene::intersect",
           "Scene::occluded", "WatertightRay::new", "intersect_triangle"]
NOT_TRACING = ["build_node", "binning::", "build_bvh", "raysets::", "RaySets::generate", "camera::"]


def classify(frames, counts):
    joined = "\n".join(frames)
    if any(k in joined for k in NOT_TRACING) or not any(k in joined for k in TRACING):
        return False
    for f in frames:
        for name, keys in RULES:
            if any(k in f for k in keys):
                counts[name] += 1
                return True
    counts["other (hit records, rayon, glue)"] += 1
    return True


def main():
    counts = collections.Counter()
    total = traced = 0
    frames = []
    for line in list(sys.stdin) + [""]:
        line = line.strip()
        if line:
            frames.append(line)
            continue
        if frames:
            total += 1
            traced += classify(frames, counts)
            frames = []
    for name, n in counts.most_common():
        print(f"{100.0 * n / max(traced, 1):6.1f}%  {name}")
    print(f"({traced} of {total} samples taken while tracing)")


main()
