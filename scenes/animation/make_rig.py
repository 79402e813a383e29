#!/usr/bin/env python3
"""Skinning and morph targets against Blender (issue 13). Builds a small rig in Blender 4.5 (bpy):
a 12-segment bar skinned to a two-bone armature (weights blending over the middle) with one shape
key, the upper bone bending 90° and the shape key going 0 → 1 over frames 1–24; exports it with
Blender's glTF exporter at its defaults (rig.glb); then imports that file into an empty scene and
records the imported object's evaluated vertex positions at frames 1, 12 and 24 in glTF's Y-up
axes (rig_pose.json). renderer/tests/animation.rs poses rig.glb at the same frames and compares.

    pip install bpy==4.5.4
    python3 scenes/animation/make_rig.py
"""
import json
import os

import bpy

HERE = os.path.dirname(os.path.abspath(__file__))
FRAMES = [1, 12, 24]


def build():
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.fps = 24
    scene.frame_start, scene.frame_end = 1, 24
    # The bar: 0.2 × 0.2 × 2, 12 segments along z.
    import math
    verts, faces = [], []
    for r in range(13):
        for k in range(8):
            a = 2 * math.pi * k / 8
            verts.append((0.1 * math.cos(a), 0.1 * math.sin(a), 2.0 * r / 12))
    for r in range(12):
        for k in range(8):
            i, j = r * 8 + k, r * 8 + (k + 1) % 8
            faces.append((i, j, j + 8, i + 8))
    me = bpy.data.meshes.new("bar")
    me.from_pydata(verts, [], faces)
    bar = bpy.data.objects.new("bar", me)
    scene.collection.objects.link(bar)
    # Armature: bone A 0 → 1, bone B 1 → 2 (z).
    bpy.ops.object.armature_add(location=(0, 0, 0))
    arm = bpy.context.object
    bpy.ops.object.mode_set(mode="EDIT")
    a = arm.data.edit_bones[0]
    a.name, a.head, a.tail = "A", (0, 0, 0), (0, 0, 1)
    b = arm.data.edit_bones.new("B")
    b.head, b.tail, b.parent = (0, 0, 1), (0, 0, 2), a
    bpy.ops.object.mode_set(mode="OBJECT")
    # Weights by height: all A below 0.7, all B above 1.3, linear between.
    ga, gb = bar.vertex_groups.new(name="A"), bar.vertex_groups.new(name="B")
    for v in bar.data.vertices:
        z = (bar.matrix_world @ v.co).z
        wb = min(1.0, max(0.0, (z - 0.7) / 0.6))
        if wb < 1.0:
            ga.add([v.index], 1.0 - wb, "REPLACE")
        if wb > 0.0:
            gb.add([v.index], wb, "REPLACE")
    mod = bar.modifiers.new("Armature", "ARMATURE")
    mod.object = arm
    bar.parent = arm
    # Shape key: the top half swells outwards.
    bar.shape_key_add(name="Basis")
    key = bar.shape_key_add(name="swell")
    for i, v in enumerate(bar.data.vertices):
        co = v.co.copy()
        if (bar.matrix_world @ co).z > 1.0:
            key.data[i].co = (co.x * 1.8, co.y * 1.8, co.z)
    # Animation: bone B bends 90° about x, the shape key goes 0 → 1.
    pb = arm.pose.bones["B"]
    pb.rotation_mode = "XYZ"
    for f, angle, w in [(1, 0.0, 0.0), (24, 1.5708, 1.0)]:
        pb.rotation_euler = (angle, 0, 0)
        pb.keyframe_insert("rotation_euler", frame=f)
        key.value = w
        key.keyframe_insert("value", frame=f)
    path = os.path.join(HERE, "rig.glb")
    bpy.ops.export_scene.gltf(filepath=path)
    return path


def evaluate(path):
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    scene.render.fps = 24
    bpy.ops.import_scene.gltf(filepath=path)
    # The importer makes one glTF animation active and stashes the others as muted NLA tracks;
    # every animation plays together here, as in Tessera's default (and as Blender had them).
    owners = list(scene.objects) + [o.data.shape_keys for o in scene.objects if o.type == "MESH" and o.data.shape_keys]
    for owner in owners:
        ad = owner.animation_data
        if ad is None:
            continue
        if ad.action is None and ad.nla_tracks and ad.nla_tracks[0].strips:
            ad.action = ad.nla_tracks[0].strips[0].action
            # Blender 4.4+ actions have slots: the action animates nothing until one is chosen.
            if hasattr(ad, "action_slot") and len(ad.action.slots) > 0:
                ad.action_slot = ad.action.slots[0]
    meshes = [o for o in scene.objects if o.type == "MESH" and o.name.startswith("bar")]
    out = {}
    for f in FRAMES:
        scene.frame_set(f)
        dg = bpy.context.evaluated_depsgraph_get()
        pts = []
        for o in meshes:
            ev = o.evaluated_get(dg)
            m = ev.to_mesh()
            for v in m.vertices:
                w = ev.matrix_world @ v.co
                pts.append([w.x, w.z, -w.y])  # Blender Z-up -> glTF Y-up
            ev.to_mesh_clear()
        out[str(f)] = pts
    with open(os.path.join(HERE, "rig_pose.json"), "w") as fh:
        json.dump({"fps": 24, "frames": out}, fh)


if __name__ == "__main__":
    evaluate(build())
