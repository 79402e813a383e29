#!/usr/bin/env python3
"""Blender round trip (issue 12): builds a small scene in Blender 4.5 (bpy), exports it with Blender's own
glTF exporter at its defaults (plus "Punctual Lights" and "Cameras", off by default), and renders it with Cycles, so Tessera can be compared with what the user
saw in Blender.

    pip install bpy==4.5.4
    python3 scenes/blender/make_blender_scene.py            # writes lights.glb and lights_cycles.exr here
    python3 scenes/blender/make_blender_scene.py materials  # writes materials.glb and materials_cycles.exr

The scene: a grey floor and a box (Principled BSDF, roughness 1, so the two renderers' BRDF models differ
least), a 300 W point light and a 2 W/m² sun (radius and angle 0: delta lights in both renderers), a
black world, 160x120, 1024 spp, 8 bounces, box filter, no denoising. The exporter writes the lights in
photometric units (W·683/4π cd and W/m²·683 lux); Tessera's `--light-units auto` recognises the exporter
by `asset.generator` and converts back, so the brightness matches Cycles.
"""
import os
import sys

import bpy

HERE = os.path.dirname(os.path.abspath(__file__))
W, H, SPP, BOUNCES = 160, 120, 1024, 8


def main():
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene

    def material(name, rgb):
        m = bpy.data.materials.new(name)
        m.use_nodes = True
        p = m.node_tree.nodes["Principled BSDF"]
        p.inputs["Base Color"].default_value = (*rgb, 1.0)
        p.inputs["Roughness"].default_value = 1.0
        p.inputs["Metallic"].default_value = 0.0
        return m

    bpy.ops.mesh.primitive_plane_add(size=10.0, location=(0, 0, 0))
    bpy.context.object.data.materials.append(material("floor", (0.5, 0.5, 0.5)))
    bpy.ops.mesh.primitive_cube_add(size=1.2, location=(0.3, 0.2, 0.6), rotation=(0, 0, 0.4))
    bpy.context.object.data.materials.append(material("box", (0.8, 0.3, 0.2)))

    point = bpy.data.lights.new("point", type="POINT")
    point.energy = 300.0
    point.shadow_soft_size = 0.0
    o = bpy.data.objects.new("point", point)
    o.location = (-1.5, -1.0, 2.5)
    scene.collection.objects.link(o)
    sun = bpy.data.lights.new("sun", type="SUN")
    sun.energy = 2.0
    sun.angle = 0.0
    o = bpy.data.objects.new("sun", sun)
    o.rotation_euler = (0.6, 0.3, 0.8)
    scene.collection.objects.link(o)

    cam = bpy.data.cameras.new("camera")
    cam.lens_unit = "FOV"
    cam.angle = 0.9
    o = bpy.data.objects.new("camera", cam)
    o.location = (4.0, -5.0, 3.2)
    scene.collection.objects.link(o)
    direction = -o.location.normalized()
    o.rotation_euler = direction.to_track_quat("-Z", "Y").to_euler()
    scene.camera = o

    world = bpy.data.worlds.new("world")
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.0
    scene.world = world

    render_settings(scene, "lights_cycles.exr")

    # Defaults, but for the two boxes a user ticks to take lights and camera along (both off by default).
    bpy.ops.export_scene.gltf(filepath=os.path.join(HERE, "lights.glb"), export_lights=True, export_cameras=True)
    import time
    t = time.time()
    bpy.ops.render.render(write_still=True)
    print(f"cycles: {W}x{H} {SPP} spp in {time.time() - t:.1f}s -> {scene.render.filepath}", file=sys.stderr)


def materials():
    """The issue's user scene: Principled materials with a Mapping node on an image texture, a
    clear-coated paint, a sheen cloth, glass, an emissive panel, point/spot/sun lights and a constant
    grey world (the exporter writes no world; Tessera's test gives it the same uniform environment).
    Exported at the exporter's defaults (plus lights and camera)."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene

    def principled(name, rgb, roughness=1.0, **inputs):
        m = bpy.data.materials.new(name)
        m.use_nodes = True
        p = m.node_tree.nodes["Principled BSDF"]
        p.inputs["Base Color"].default_value = (*rgb, 1.0)
        p.inputs["Roughness"].default_value = roughness
        p.inputs["Metallic"].default_value = 0.0
        for k, v in inputs.items():
            p.inputs[k.replace("_", " ")].default_value = v
        return m, p

    # Floor: an image texture through a Mapping node (-> KHR_texture_transform, required).
    floor, p = principled("floor", (0.5, 0.5, 0.5))
    img = bpy.data.images.new("grid", 64, 64)
    img.generated_type = "COLOR_GRID"
    img.pack()
    nt = floor.node_tree
    tex = nt.nodes.new("ShaderNodeTexImage")
    tex.image = img
    mapping = nt.nodes.new("ShaderNodeMapping")
    mapping.inputs["Scale"].default_value = (3.0, 3.0, 1.0)
    coords = nt.nodes.new("ShaderNodeTexCoord")
    nt.links.new(coords.outputs["UV"], mapping.inputs["Vector"])
    nt.links.new(mapping.outputs["Vector"], tex.inputs["Vector"])
    nt.links.new(tex.outputs["Color"], p.inputs["Base Color"])
    bpy.ops.mesh.primitive_plane_add(size=10.0, location=(0, 0, 0))
    bpy.context.object.data.materials.append(floor)

    paint, _ = principled("paint", (0.6, 0.08, 0.05), 0.5, Coat_Weight=1.0, Coat_Roughness=0.05)
    cloth, _ = principled("cloth", (0.15, 0.25, 0.6), 1.0, Sheen_Weight=1.0, Sheen_Roughness=0.5)
    glass, _ = principled("glass", (1.0, 1.0, 1.0), 0.0, Transmission_Weight=1.0, IOR=1.5)
    for mat, loc in [(paint, (-1.4, 0.4, 0.6)), (cloth, (0.0, 0.9, 0.6)), (glass, (1.3, -0.2, 0.6))]:
        bpy.ops.mesh.primitive_uv_sphere_add(radius=0.6, location=loc, segments=48, ring_count=24)
        bpy.ops.object.shade_smooth()
        bpy.context.object.data.materials.append(mat)

    panel, p = principled("panel", (0.0, 0.0, 0.0))
    p.inputs["Emission Color"].default_value = (1.0, 0.9, 0.7, 1.0)
    p.inputs["Emission Strength"].default_value = 4.0
    bpy.ops.mesh.primitive_plane_add(size=1.0, location=(0.0, 2.5, 1.2), rotation=(1.5708, 0.0, 0.0))
    bpy.context.object.data.materials.append(panel)

    for kind, energy, loc, rot in [
        ("POINT", 200.0, (-2.0, -1.5, 2.5), (0, 0, 0)),
        ("SPOT", 400.0, (2.5, -2.0, 3.0), (0.7, 0.0, 0.9)),
        ("SUN", 1.5, (0, 0, 5), (0.6, 0.3, 0.8)),
    ]:
        light = bpy.data.lights.new(kind.lower(), type=kind)
        light.energy = energy
        if kind == "SUN":
            light.angle = 0.0
        else:
            light.shadow_soft_size = 0.0
        if kind == "SPOT":
            light.spot_size = 1.0
            light.spot_blend = 0.15
        o = bpy.data.objects.new(kind.lower(), light)
        o.location = loc
        o.rotation_euler = rot
        scene.collection.objects.link(o)

    cam = bpy.data.cameras.new("camera")
    cam.lens_unit = "FOV"
    cam.angle = 0.9
    o = bpy.data.objects.new("camera", cam)
    o.location = (3.5, -5.5, 3.0)
    scene.collection.objects.link(o)
    o.rotation_euler = (-(o.location - __import__("mathutils").Vector((0, 0.3, 0.5)))).to_track_quat("-Z", "Y").to_euler()
    scene.camera = o

    world = bpy.data.worlds.new("world")
    world.use_nodes = True
    bg = world.node_tree.nodes["Background"]
    bg.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
    bg.inputs["Strength"].default_value = WORLD
    scene.world = world
    render_settings(scene, "materials_cycles.exr")
    bpy.ops.export_scene.gltf(filepath=os.path.join(HERE, "materials.glb"), export_lights=True, export_cameras=True)
    import time
    t = time.time()
    bpy.ops.render.render(write_still=True)
    print(f"cycles: {W}x{H} {SPP} spp in {time.time() - t:.1f}s -> {scene.render.filepath}", file=sys.stderr)


# The materials scene's uniform world radiance (Tessera's test uses the same).
WORLD = 0.1


def render_settings(scene, out):
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = SPP
    scene.cycles.use_adaptive_sampling = False
    scene.cycles.use_denoising = False
    scene.cycles.max_bounces = BOUNCES
    scene.cycles.diffuse_bounces = BOUNCES
    scene.cycles.glossy_bounces = BOUNCES
    scene.cycles.transmission_bounces = BOUNCES
    scene.cycles.sample_clamp_direct = 0.0
    scene.cycles.sample_clamp_indirect = 0.0
    scene.cycles.caustics_reflective = True
    scene.cycles.caustics_refractive = True
    scene.cycles.filter_type = "BOX"
    scene.cycles.pixel_filter_type = "BOX"
    scene.render.resolution_x, scene.render.resolution_y = W, H
    scene.render.resolution_percentage = 100
    scene.view_settings.view_transform = "Standard"
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.image_settings.color_depth = "32"
    scene.render.filepath = os.path.join(HERE, out)


if __name__ == "__main__":
    if sys.argv[1:] == ["materials"]:
        materials()
    else:
        main()
