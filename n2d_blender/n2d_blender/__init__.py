"""n2d's small bpy layer, shaped like BlenderProc's API: objects, materials, lighting, camera, physics, renderer.

Plain functions on Blender's data API (operators need a UI context; the data API does not). Import it
only inside a render worker process: bpy holds global state, costs ~0.5 GB and is not thread-safe.
"""
