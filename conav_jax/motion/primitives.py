"""The vocabulary of motion primitives an activity is animated with.

Each activity of the activity graph (conav_jax/data/activity_graph.json) names one primitive;
conav_jax.motion turns (primitive, activity id) into a keyframe clip whose parameters (tempo,
amplitude, hand, height) are derived from the activity id, so every activity has its own
recognisable signature even when two share a primitive.
"""

MOTION_PRIMITIVES: dict[str, str] = {
    "stand_idle": "stands, weight shifting, small head turns",
    "reach_up": "reaches one or both hands above the head (ceiling lamp, top shelf)",
    "reach_forward": "reaches forward at chest height (cabinet, fridge, shelf)",
    "bend_down": "bends at the hips to reach near the floor",
    "crouch": "knees bent, low squat, hands near the floor",
    "sit": "sits down on a seat-height surface and stays seated",
    "lie_down": "lowers the body to lie on a bed-height surface",
    "wipe": "circular hand motion at a surface (cleaning, wiping)",
    "stir": "small circular hand motion at counter height (cooking, baking)",
    "type": "both hands moving slightly at desk height (working, typing)",
    "pick_and_place": "picks something up at waist height and puts it down again",
    "carry": "holds both hands in front of the chest, as if carrying",
    "open_door": "pulls a handle open with one arm, steps back",
    "look_in_mirror": "faces the wall, head tilting, one hand near the face",
    "arms_overhead_stretch": "stretches both arms overhead, side bends",
    "wash_body": "both hands moving over the body (showering)",
    "walk_in_place": "steps in place (treadmill, exercise)",
    "play_instrument": "seated or standing, both hands moving at keyboard height",
    "drink": "raises one hand to the mouth repeatedly",
    "hang_on_wall": "lifts an object with both hands to the wall at eye height",
}
