"""DMControl's instructions to labellers (`runvocab.instructions`), written from each task's
reward in dm_control's suite sources."""

from __future__ import annotations

from runvocab.tie_sentences import NEITHER, RARE, ties

# (goal, what decides), by task name without the family prefix.

DMC: dict[str, tuple[str, str]] = {
    "acrobot_swingup": (
        "Swing the two-link arm up so its tip reaches the top, straight above the pivot, and "
        "stays there.",
        "Prefer the clip whose tip spends more time at the top; otherwise the one whose tip is "
        "nearer the top on the whole. Spinning past the top counts only while the tip is near "
        f"it. {RARE}",
    ),
    "acrobot_swingup_sparse": (
        "Swing the two-link arm up so its tip is inside the small target straight above the "
        "pivot.",
        "Only time with the tip inside the target counts: prefer the clip that keeps it there "
        f"longer. Nearly reaching it counts nothing. {ties('gets its tip into it', True)}",
    ),
    "ball_in_cup_catch": (
        "Swing the ball on its string up and catch it in the cup.",
        "Only time with the ball inside the cup counts: prefer the clip where it is in the cup "
        f"longer. Near misses count nothing. {NEITHER}",
    ),
    "cartpole_balance": (
        "Keep the pole balanced upright on the cart, with the cart near the middle of the track.",
        "Prefer the clip whose pole stays nearer vertical. If both stay up, prefer the one "
        "with the cart nearer the middle, then the calmer one: slower pole swings and gentler "
        f"pushes. {RARE}",
    ),
    "cartpole_balance_sparse": (
        "Keep the pole within a few degrees of vertical and the cart in the middle quarter of "
        "the track.",
        "Only time inside both limits counts: prefer the clip that stays inside them longer. "
        f"How close a fallen pole came counts nothing. {ties('stays inside them')}",
    ),
    "cartpole_swingup": (
        "Swing the pole up from hanging down, then balance it upright with the cart near the "
        "middle of the track.",
        "Prefer the clip whose pole is upright more of the time (higher is better even before "
        "it is balanced). Then the cart nearer the middle, then the calmer balance: slower pole "
        f"swings and gentler pushes. {RARE}",
    ),
    "cartpole_swingup_sparse": (
        "Swing the pole up from hanging down and hold it within a few degrees of vertical, with "
        "the cart in the middle quarter of the track.",
        "Only time inside both limits counts: prefer the clip that stays inside them longer. "
        f"Swinging high without holding counts nothing. {ties('holds it there', True)}",
    ),
    "cartpole_two_poles": (
        "Balance both stacked poles upright on the cart, with the cart near the middle of the "
        "track.",
        "Prefer the clip whose poles are, on average, nearer vertical more of the time. Then "
        f"the cart nearer the middle, then the calmer one: slower swings, gentler pushes. {RARE}",
    ),
    "cartpole_three_poles": (
        "Balance all three stacked poles upright on the cart, with the cart near the middle of "
        "the track.",
        "Prefer the clip whose poles are, on average, nearer vertical more of the time. Then "
        f"the cart nearer the middle, then the calmer one: slower swings, gentler pushes. {RARE}",
    ),
    "cheetah_run": (
        "Run forward (to the right) as fast as possible.",
        "Prefer the clip where the cheetah moves forward faster, up to a full sprint (at 1×, "
        "about three of the posts behind it go by each second; they stand a metre apart); "
        "faster gains nothing. If the speeds look alike, prefer the one that covers more "
        "ground. Only forward speed counts: a flipped cheetah that moves forward fast beats an "
        "upright one that stands still, and moving backwards counts as little as standing "
        f"still. {ties('moves forward')}",
    ),
    "dog_stand": (
        "Stand up on all four legs, with torso and hips at full standing height and the body "
        "level.",
        "Prefer the clip where the dog stands taller and more level (head, torso and hips "
        "upright), without straining its joints against their limits. Moving about does not "
        f"matter. {RARE}",
    ),
    "dog_walk": (
        "Stand tall and walk forward at a steady walk.",
        "First the dog must stand (torso and hips at standing height, body level). Then prefer "
        "the clip walking forward steadily, up to twice a steady walk's pace; slower is worse, "
        f"and faster gains nothing. Moving sideways or backwards does not count. {RARE}",
    ),
    "dog_trot": (
        "Stand tall and trot forward.",
        "First the dog must stand (torso and hips at standing height, body level). Then prefer "
        "the clip trotting forward, at up to twice a trot's pace; slower is worse, and faster "
        f"gains nothing. {RARE}",
    ),
    "dog_run": (
        "Stand tall and run forward fast.",
        "First the dog must stay up (torso and hips at standing height, body level). Then "
        "prefer the faster clip, up to a full gallop; moving sideways or backwards does not "
        f"count. {RARE}",
    ),
    "dog_fetch": (
        "Fetch the ball: get it in the mouth and bring it to the target in the arena, while "
        "standing.",
        "Prefer the clip with the ball nearer the target; then the one whose mouth is nearer "
        f"the ball. Throughout, standing tall and level is better than lying down. {RARE}",
    ),
    "finger_spin": (
        "Flick the spinner (the long pole on the hinge) so that it spins fast, clockwise as "
        "seen in the clip.",
        "Only fast clockwise spinning counts (a blur, not a turn you can follow): prefer the "
        "clip that keeps it spinning that fast for longer. Slow turns and counter-clockwise "
        f"spins count nothing. {ties('spins it that fast', True)}",
    ),
    "finger_turn_easy": (
        "Turn the spinner so that its tip reaches the target circle and stays there.",
        "Only time with the tip inside the target counts: prefer the clip that keeps it there "
        f"longer. {ties('gets the tip into it', True)}",
    ),
    "finger_turn_hard": (
        "Turn the spinner so that its tip reaches the small target circle and stays there.",
        "Only time with the tip inside the target (smaller than in the easy task) counts: "
        f"prefer the clip that keeps it there longer. {ties('gets the tip into it', True)}",
    ),
    "fish_upright": (
        "Keep the fish upright: back up, belly down.",
        "Prefer the clip where the fish is nearer upright more of the time; where it swims does "
        f"not matter. {RARE}",
    ),
    "fish_swim": (
        "Swim so that the fish's mouth reaches the target ball, staying upright.",
        "Reaching the target counts most (7 parts in 8): prefer the clip whose mouth is at or "
        f"nearer the target longer. Then the fish nearer upright (1 part in 8). {RARE}",
    ),
    "hopper_stand": (
        "Stand up on the one leg with the body high, and keep still.",
        "Only the body up high counts: at least about two thirds as high above its foot as "
        "when it stands straight (crouched lower or lying down counts nothing). Prefer the "
        "clip that is up high longer; then the one that needs gentler pushes to stay there. "
        f"{ties('gets its body up that high', True)}",
    ),
    "hopper_hop": (
        "Hop forward (to the right) while staying tall.",
        "The body must be up high: at least about two thirds as high above its foot as when "
        "it stands straight (crouched lower or lying down counts nothing, however it moves). "
        "Then prefer the clip hopping forward faster, up to a quick hop (at 1×, one or two of "
        "the posts behind it, a metre apart, going by each second); faster gains nothing. "
        f"{ties('hops forward with its body up that high', True)}",
    ),
    "humanoid_stand": (
        "Stand up straight and stay in place.",
        "Prefer the clip where the head is higher (nearly as high as standing straight counts "
        "fully) and the torso more upright; then the one that moves about less and uses gentler "
        f"effort. {RARE}",
    ),
    "humanoid_walk": (
        "Stand up straight and walk.",
        "First the body must be up: head nearly as high as standing straight, torso upright; a "
        "fallen humanoid scores next to nothing. Then prefer the clip moving faster over the "
        f"ground, in any direction, up to a walking pace; then gentler effort. {RARE}",
    ),
    "humanoid_run": (
        "Stand up straight and run as fast as possible.",
        "First the body must be up: head nearly as high as standing straight, torso upright; a "
        "fallen humanoid scores next to nothing. Then prefer the clip moving faster over the "
        "ground, in any direction, up to a sprint (ten times a walking pace); then gentler "
        f"effort. {RARE}",
    ),
    "humanoid_run_pure_state": (
        "Stand up straight and run as fast as possible.",
        "First the body must be up: head nearly as high as standing straight, torso upright; a "
        "fallen humanoid scores next to nothing. Then prefer the clip moving faster over the "
        "ground, in any direction, up to a sprint (ten times a walking pace); then gentler "
        f"effort. {RARE}",
    ),
    "humanoid_CMU_stand": (
        "Stand up straight and stay in place.",
        "Prefer the clip where the head is higher (nearly as high as standing straight counts "
        "fully) and the chest more upright; then the one that moves about less and uses gentler "
        f"effort. {RARE}",
    ),
    "humanoid_CMU_walk": (
        "Stand up straight and walk.",
        "First the body must be up: head nearly as high as standing straight, chest upright; a "
        "fallen humanoid scores next to nothing. Then prefer the clip moving faster over the "
        f"ground, in any direction, up to a walking pace; then gentler effort. {RARE}",
    ),
    "humanoid_CMU_run": (
        "Stand up straight and run as fast as possible.",
        "First the body must be up: head nearly as high as standing straight, chest upright; a "
        "fallen humanoid scores next to nothing. Then prefer the clip moving faster over the "
        "ground, in any direction, up to a sprint (ten times a walking pace); then gentler "
        f"effort. {RARE}",
    ),
    "lqr_lqr_2_1": (
        "Bring the two bodies on their springs to rest at their middle positions, pushing "
        "gently.",
        "Prefer the clip where the bodies are nearer their middle positions; then the one that "
        f"pushes less hard. {RARE}",
    ),
    "lqr_lqr_6_2": (
        "Bring the six bodies on their springs to rest at their middle positions, pushing "
        "gently.",
        "Prefer the clip where the bodies are nearer their middle positions; then the one that "
        f"pushes less hard. {RARE}",
    ),
    "manipulator_bring_ball": (
        "Pick up the ball and bring it to the target (the faint ball outline).",
        "Only the ball at the target counts: prefer the clip where it is there, or touching "
        "the outline, longer. Holding the ball elsewhere counts nothing. "
        f"{NEITHER}",
    ),
    "manipulator_bring_peg": (
        "Grasp the peg and bring it to the target (the faint peg outline), lined up with it.",
        "Prefer the clip where the peg sits in the target outline, both ends lined up; short "
        "of that, a clip where the hand grips the peg properly (pinched between the fingers) "
        "beats one where it does not. "
        f"{ties('grips the peg or brings it near the outline')}",
    ),
    "manipulator_insert_ball": (
        "Pick up the ball and put it into the cup.",
        "Only the ball in the cup counts: prefer the clip where it is there longer. Holding "
        f"the ball elsewhere counts nothing. {NEITHER}",
    ),
    "manipulator_insert_peg": (
        "Grasp the peg and insert it into the slot, lined up with it.",
        "Prefer the clip where the peg sits in the slot, both ends lined up; short of that, a "
        "clip where the hand grips the peg properly (pinched between the fingers) beats one "
        f"where it does not. {ties('grips the peg or brings it near the slot')}",
    ),
    "pendulum_swingup": (
        "Swing the pendulum up and hold it pointing straight up.",
        "Only time within a few degrees of straight up counts: prefer the clip that holds it "
        f"there longer. Swinging high without holding counts nothing. "
        f"{ties('gets it there', True)}",
    ),
    "point_mass_easy": (
        "Move the ball to the target in the middle and keep it there, pushing gently.",
        "Prefer the clip whose ball is at or nearer the target longer; then the one pushing "
        f"less hard. {RARE}",
    ),
    "point_mass_hard": (
        "Move the ball to the target in the middle and keep it there, pushing gently.",
        "Prefer the clip whose ball is at or nearer the target longer; then the one pushing "
        f"less hard. {RARE}",
    ),
    "quadruped_walk": (
        "Stay upright and walk forward, the way the body faces.",
        "First, upright beats tipped over: a body on its back scores nothing. If both are "
        "upright, or neither, prefer the one moving forward faster: a steady walk counts "
        "fully, slower counts partly, backwards not at all. If both move alike, prefer the one "
        f"whose body is higher off the ground. {RARE}",
    ),
    "quadruped_run": (
        "Stay upright and run forward, the way the body faces, as fast as possible.",
        "First, upright beats tipped over: a body on its back scores nothing. If both are "
        "upright, or neither, prefer the one moving forward faster, up to a fast run (ten "
        "times a steady walk); faster gains nothing. If both move alike, prefer the one whose "
        f"body is higher off the ground. {RARE}",
    ),
    "quadruped_escape": (
        "Climb out of the bumpy bowl: get as far from the starting point as possible, staying "
        "upright.",
        "Prefer the clip that ends farther from where the body started; the body must stay "
        f"upright (tilted a little counts fully, on its back nothing). {RARE}",
    ),
    "quadruped_fetch": (
        "Reach the ball and push it to the target in the middle of the arena.",
        "Prefer the clip with the ball nearer the target, with the body close to the ball; "
        f"short of that, the one that gets nearer the ball. {RARE}",
    ),
    "reacher_easy": (
        "Touch the target with the tip of the arm and stay there.",
        "Only time with the fingertip on the target counts: prefer the clip that keeps it "
        f"there longer. {ties('gets there', True)}",
    ),
    "reacher_hard": (
        "Touch the small target with the tip of the arm and stay there.",
        "Only time with the fingertip on the target (smaller than in the easy task) counts: "
        f"prefer the clip that keeps it there longer. {ties('gets there', True)}",
    ),
    "stacker_stack_2": (
        "Put one of the two boxes on the target spot, then move the hand away from it.",
        "Prefer the clip where a box is nearer the target spot, with the hand clear of it "
        "(about a box's width or more away); a box on the target with the hand still on it "
        f"counts nothing. {ties('brings a box near the target spot')}",
    ),
    "stacker_stack_4": (
        "Put one of the four boxes on the target spot, then move the hand away from it.",
        "Prefer the clip where a box is nearer the target spot, with the hand clear of it "
        "(about a box's width or more away); a box on the target with the hand still on it "
        f"counts nothing. {ties('brings a box near the target spot')}",
    ),
    "swimmer_swimmer6": (
        "Swim so that the swimmer's nose reaches the target.",
        "Prefer the clip whose nose is at or nearer the target; the nearer, the better, even "
        f"from far away. {RARE}",
    ),
    "swimmer_swimmer15": (
        "Swim so that the swimmer's nose reaches the target.",
        "Prefer the clip whose nose is at or nearer the target; the nearer, the better, even "
        f"from far away. {RARE}",
    ),
    "walker_stand": (
        "Stand upright with the body high.",
        "Prefer the clip whose body is higher (nearly as high as standing straight counts "
        f"fully) and more upright; moving does not matter. {RARE}",
    ),
    "walker_walk": (
        "Stand upright, then walk forward (to the right).",
        "First, prefer the walker that stands upright with its body high (nearly as high as "
        "standing straight). If both stand, or neither, prefer the one moving right faster, up "
        "to a walking pace (at 1×, about one of the posts behind it, a metre apart, going by "
        "each second); faster gains nothing. If the speeds are close, prefer the one that "
        f"covers more ground. {RARE}",
    ),
    "walker_run": (
        "Stand upright, then run forward (to the right) as fast as possible.",
        "First, prefer the walker that stands upright with its body high (nearly as high as "
        "standing straight). If both stand, or neither, prefer the one moving right faster, up "
        "to a sprint (at 1×, about seven of the posts behind it, a metre apart, going by each "
        "second). If the speeds are close, prefer the one that covers more ground. "
        f"{RARE}",
    ),
}
