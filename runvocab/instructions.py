"""What a labeller is told "better" means, per task: the goal in one line, then what decides
between two clips, in order. Written from each task's reward (dm_control's suite sources,
Metaworld v3's `compute_reward`), so that people prefer what the reward prefers.

A run shows its own instruction when an operator gave one (`runs.instruction`), else
`default_instruction(task)`: the text below for a known task, or a generic one built from the
task's name. Data only: no torch, no MuJoCo (the server imports it).
"""

from __future__ import annotations

import hashlib

MAX_CHARS = 2000
"""the longest instruction an operator may store"""

OFTEN_SHARE = 0.5
"""a tie sentence says ties are common early on ("often") when at least this share of the pairs
of random-action segments have exactly equal returns (`trainer.tie_check`)"""
RARE_SHARE = 0.01
"""a tie sentence says exact ties are rare when fewer than this share of pairs tie, with random
actions and with none"""

# Every task's text ends with one tie sentence, one of three kinds (`tie_kind`), chosen from what
# its reward does and checked against it (`trainer.tie_check`, tests/trainer/test_tie_check.py):
# "often" and "sometimes" name what makes both clips score nothing (the reward is exactly 0
# then, so the scripted teacher, and the truth a labeller is scored against, says "equal");
# "rare" where the reward never stops telling two clips apart.
_OFTEN_TAIL = " Early in training most pairs are like that."
_RARE = ("Two clips are hardly ever exactly as good as each other: if they look alike, prefer "
         "the one that is even slightly better.")


def _ties(condition: str, often: bool = False) -> str:
    """The tie sentence of a reward that is exactly 0 unless `condition` holds."""
    return f"If neither clip {condition}, they are equally good." + (_OFTEN_TAIL if often else "")


# Shared endings, so that every task says what to do when a clip shows nothing of the goal.
_NEITHER = _ties("gets there")
_CLOSER = "If neither finishes, prefer the one that gets closer to finishing."

# ---- DMControl ---------------------------------------------------------------------------
# (goal, what decides), by task name without the family prefix.

_DMC: dict[str, tuple[str, str]] = {
    "acrobot_swingup": (
        "Swing the two-link arm up so its tip reaches the top, straight above the pivot, and "
        "stays there.",
        "Prefer the clip whose tip spends more time at the top; otherwise the one whose tip is "
        "nearer the top on the whole. Spinning past the top counts only while the tip is near "
        f"it. {_RARE}",
    ),
    "acrobot_swingup_sparse": (
        "Swing the two-link arm up so its tip is inside the small target straight above the "
        "pivot.",
        "Only time with the tip inside the target counts: prefer the clip that keeps it there "
        f"longer. Nearly reaching it counts nothing. {_ties('gets its tip into it', True)}",
    ),
    "ball_in_cup_catch": (
        "Swing the ball on its string up and catch it in the cup.",
        "Only time with the ball inside the cup counts: prefer the clip where it is in the cup "
        f"longer. Near misses count nothing. {_NEITHER}",
    ),
    "cartpole_balance": (
        "Keep the pole balanced upright on the cart, with the cart near the middle of the track.",
        "Prefer the clip whose pole stays nearer vertical. If both stay up, prefer the one "
        "with the cart nearer the middle, then the calmer one: slower pole swings and gentler "
        f"pushes. {_RARE}",
    ),
    "cartpole_balance_sparse": (
        "Keep the pole within a few degrees of vertical and the cart in the middle quarter of "
        "the track.",
        "Only time inside both limits counts: prefer the clip that stays inside them longer. "
        f"How close a fallen pole came counts nothing. {_ties('stays inside them')}",
    ),
    "cartpole_swingup": (
        "Swing the pole up from hanging down, then balance it upright with the cart near the "
        "middle of the track.",
        "Prefer the clip whose pole is upright more of the time (higher is better even before "
        "it is balanced). Then the cart nearer the middle, then the calmer balance: slower pole "
        f"swings and gentler pushes. {_RARE}",
    ),
    "cartpole_swingup_sparse": (
        "Swing the pole up from hanging down and hold it within a few degrees of vertical, with "
        "the cart in the middle quarter of the track.",
        "Only time inside both limits counts: prefer the clip that stays inside them longer. "
        f"Swinging high without holding counts nothing. {_ties('holds it there', True)}",
    ),
    "cartpole_two_poles": (
        "Balance both stacked poles upright on the cart, with the cart near the middle of the "
        "track.",
        "Prefer the clip whose poles are, on average, nearer vertical more of the time. Then "
        f"the cart nearer the middle, then the calmer one: slower swings, gentler pushes. {_RARE}",
    ),
    "cartpole_three_poles": (
        "Balance all three stacked poles upright on the cart, with the cart near the middle of "
        "the track.",
        "Prefer the clip whose poles are, on average, nearer vertical more of the time. Then "
        f"the cart nearer the middle, then the calmer one: slower swings, gentler pushes. {_RARE}",
    ),
    "cheetah_run": (
        "Run forward (to the right) as fast as possible.",
        "Prefer the clip where the cheetah moves forward faster, up to a full sprint (at 1×, "
        "about three of the posts behind it go by each second; they stand a metre apart); "
        "faster gains nothing. If the speeds look alike, prefer the one that covers more "
        "ground. Only forward speed counts: a flipped cheetah that moves forward fast beats an "
        "upright one that stands still, and moving backwards counts as little as standing "
        f"still. {_ties('moves forward')}",
    ),
    "dog_stand": (
        "Stand up on all four legs, with torso and hips at full standing height and the body "
        "level.",
        "Prefer the clip where the dog stands taller and more level (head, torso and hips "
        "upright), without straining its joints against their limits. Moving about does not "
        f"matter. {_RARE}",
    ),
    "dog_walk": (
        "Stand tall and walk forward at a steady walk.",
        "First the dog must stand (torso and hips at standing height, body level). Then prefer "
        "the clip walking forward steadily, up to twice a steady walk's pace; slower is worse, "
        f"and faster gains nothing. Moving sideways or backwards does not count. {_RARE}",
    ),
    "dog_trot": (
        "Stand tall and trot forward.",
        "First the dog must stand (torso and hips at standing height, body level). Then prefer "
        "the clip trotting forward, at up to twice a trot's pace; slower is worse, and faster "
        f"gains nothing. {_RARE}",
    ),
    "dog_run": (
        "Stand tall and run forward fast.",
        "First the dog must stay up (torso and hips at standing height, body level). Then "
        "prefer the faster clip, up to a full gallop; moving sideways or backwards does not "
        f"count. {_RARE}",
    ),
    "dog_fetch": (
        "Fetch the ball: get it in the mouth and bring it to the target in the arena, while "
        "standing.",
        "Prefer the clip with the ball nearer the target; then the one whose mouth is nearer "
        f"the ball. Throughout, standing tall and level is better than lying down. {_RARE}",
    ),
    "finger_spin": (
        "Flick the spinner (the long pole on the hinge) so that it spins fast, clockwise as "
        "seen in the clip.",
        "Only fast clockwise spinning counts (a blur, not a turn you can follow): prefer the "
        "clip that keeps it spinning that fast for longer. Slow turns and counter-clockwise "
        f"spins count nothing. {_ties('spins it that fast', True)}",
    ),
    "finger_turn_easy": (
        "Turn the spinner so that its tip reaches the target circle and stays there.",
        "Only time with the tip inside the target counts: prefer the clip that keeps it there "
        f"longer. {_ties('gets the tip into it', True)}",
    ),
    "finger_turn_hard": (
        "Turn the spinner so that its tip reaches the small target circle and stays there.",
        "Only time with the tip inside the target (smaller than in the easy task) counts: "
        f"prefer the clip that keeps it there longer. {_ties('gets the tip into it', True)}",
    ),
    "fish_upright": (
        "Keep the fish upright: back up, belly down.",
        "Prefer the clip where the fish is nearer upright more of the time; where it swims does "
        f"not matter. {_RARE}",
    ),
    "fish_swim": (
        "Swim so that the fish's mouth reaches the target ball, staying upright.",
        "Reaching the target counts most (7 parts in 8): prefer the clip whose mouth is at or "
        f"nearer the target longer. Then the fish nearer upright (1 part in 8). {_RARE}",
    ),
    "hopper_stand": (
        "Stand up on the one leg with the body high, and keep still.",
        "Only the body up high counts: at least about two thirds as high above its foot as "
        "when it stands straight (crouched lower or lying down counts nothing). Prefer the "
        "clip that is up high longer; then the one that needs gentler pushes to stay there. "
        f"{_ties('gets its body up that high', True)}",
    ),
    "hopper_hop": (
        "Hop forward (to the right) while staying tall.",
        "The body must be up high: at least about two thirds as high above its foot as when "
        "it stands straight (crouched lower or lying down counts nothing, however it moves). "
        "Then prefer the clip hopping forward faster, up to a quick hop (at 1×, one or two of "
        "the posts behind it, a metre apart, going by each second); faster gains nothing. "
        f"{_ties('hops forward with its body up that high', True)}",
    ),
    "humanoid_stand": (
        "Stand up straight and stay in place.",
        "Prefer the clip where the head is higher (nearly as high as standing straight counts "
        "fully) and the torso more upright; then the one that moves about less and uses gentler "
        f"effort. {_RARE}",
    ),
    "humanoid_walk": (
        "Stand up straight and walk.",
        "First the body must be up: head nearly as high as standing straight, torso upright; a "
        "fallen humanoid scores next to nothing. Then prefer the clip moving faster over the "
        f"ground, in any direction, up to a walking pace; then gentler effort. {_RARE}",
    ),
    "humanoid_run": (
        "Stand up straight and run as fast as possible.",
        "First the body must be up: head nearly as high as standing straight, torso upright; a "
        "fallen humanoid scores next to nothing. Then prefer the clip moving faster over the "
        "ground, in any direction, up to a sprint (ten times a walking pace); then gentler "
        f"effort. {_RARE}",
    ),
    "humanoid_run_pure_state": (
        "Stand up straight and run as fast as possible.",
        "First the body must be up: head nearly as high as standing straight, torso upright; a "
        "fallen humanoid scores next to nothing. Then prefer the clip moving faster over the "
        "ground, in any direction, up to a sprint (ten times a walking pace); then gentler "
        f"effort. {_RARE}",
    ),
    "humanoid_CMU_stand": (
        "Stand up straight and stay in place.",
        "Prefer the clip where the head is higher (nearly as high as standing straight counts "
        "fully) and the chest more upright; then the one that moves about less and uses gentler "
        f"effort. {_RARE}",
    ),
    "humanoid_CMU_walk": (
        "Stand up straight and walk.",
        "First the body must be up: head nearly as high as standing straight, chest upright; a "
        "fallen humanoid scores next to nothing. Then prefer the clip moving faster over the "
        f"ground, in any direction, up to a walking pace; then gentler effort. {_RARE}",
    ),
    "humanoid_CMU_run": (
        "Stand up straight and run as fast as possible.",
        "First the body must be up: head nearly as high as standing straight, chest upright; a "
        "fallen humanoid scores next to nothing. Then prefer the clip moving faster over the "
        "ground, in any direction, up to a sprint (ten times a walking pace); then gentler "
        f"effort. {_RARE}",
    ),
    "lqr_lqr_2_1": (
        "Bring the two bodies on their springs to rest at their middle positions, pushing "
        "gently.",
        "Prefer the clip where the bodies are nearer their middle positions; then the one that "
        f"pushes less hard. {_RARE}",
    ),
    "lqr_lqr_6_2": (
        "Bring the six bodies on their springs to rest at their middle positions, pushing "
        "gently.",
        "Prefer the clip where the bodies are nearer their middle positions; then the one that "
        f"pushes less hard. {_RARE}",
    ),
    "manipulator_bring_ball": (
        "Pick up the ball and bring it to the target (the faint ball outline).",
        "Only the ball at the target counts: prefer the clip where it is there, or touching "
        "the outline, longer. Holding the ball elsewhere counts nothing. "
        f"{_NEITHER}",
    ),
    "manipulator_bring_peg": (
        "Grasp the peg and bring it to the target (the faint peg outline), lined up with it.",
        "Prefer the clip where the peg sits in the target outline, both ends lined up; short "
        "of that, a clip where the hand grips the peg properly (pinched between the fingers) "
        "beats one where it does not. "
        f"{_ties('grips the peg or brings it near the outline')}",
    ),
    "manipulator_insert_ball": (
        "Pick up the ball and put it into the cup.",
        "Only the ball in the cup counts: prefer the clip where it is there longer. Holding "
        f"the ball elsewhere counts nothing. {_NEITHER}",
    ),
    "manipulator_insert_peg": (
        "Grasp the peg and insert it into the slot, lined up with it.",
        "Prefer the clip where the peg sits in the slot, both ends lined up; short of that, a "
        "clip where the hand grips the peg properly (pinched between the fingers) beats one "
        f"where it does not. {_ties('grips the peg or brings it near the slot')}",
    ),
    "pendulum_swingup": (
        "Swing the pendulum up and hold it pointing straight up.",
        "Only time within a few degrees of straight up counts: prefer the clip that holds it "
        f"there longer. Swinging high without holding counts nothing. "
        f"{_ties('gets it there', True)}",
    ),
    "point_mass_easy": (
        "Move the ball to the target in the middle and keep it there, pushing gently.",
        "Prefer the clip whose ball is at or nearer the target longer; then the one pushing "
        f"less hard. {_RARE}",
    ),
    "point_mass_hard": (
        "Move the ball to the target in the middle and keep it there, pushing gently.",
        "Prefer the clip whose ball is at or nearer the target longer; then the one pushing "
        f"less hard. {_RARE}",
    ),
    "quadruped_walk": (
        "Stay upright and walk forward, the way the body faces.",
        "First, upright beats tipped over: a body on its back scores nothing. If both are "
        "upright, or neither, prefer the one moving forward faster: a steady walk counts "
        "fully, slower counts partly, backwards not at all. If both move alike, prefer the one "
        f"whose body is higher off the ground. {_RARE}",
    ),
    "quadruped_run": (
        "Stay upright and run forward, the way the body faces, as fast as possible.",
        "First, upright beats tipped over: a body on its back scores nothing. If both are "
        "upright, or neither, prefer the one moving forward faster, up to a fast run (ten "
        "times a steady walk); faster gains nothing. If both move alike, prefer the one whose "
        f"body is higher off the ground. {_RARE}",
    ),
    "quadruped_escape": (
        "Climb out of the bumpy bowl: get as far from the starting point as possible, staying "
        "upright.",
        "Prefer the clip that ends farther from where the body started; the body must stay "
        f"upright (tilted a little counts fully, on its back nothing). {_RARE}",
    ),
    "quadruped_fetch": (
        "Reach the ball and push it to the target in the middle of the arena.",
        "Prefer the clip with the ball nearer the target, with the body close to the ball; "
        f"short of that, the one that gets nearer the ball. {_RARE}",
    ),
    "reacher_easy": (
        "Touch the target with the tip of the arm and stay there.",
        "Only time with the fingertip on the target counts: prefer the clip that keeps it "
        f"there longer. {_ties('gets there', True)}",
    ),
    "reacher_hard": (
        "Touch the small target with the tip of the arm and stay there.",
        "Only time with the fingertip on the target (smaller than in the easy task) counts: "
        f"prefer the clip that keeps it there longer. {_ties('gets there', True)}",
    ),
    "stacker_stack_2": (
        "Put one of the two boxes on the target spot, then move the hand away from it.",
        "Prefer the clip where a box is nearer the target spot, with the hand clear of it "
        "(about a box's width or more away); a box on the target with the hand still on it "
        f"counts nothing. {_ties('brings a box near the target spot')}",
    ),
    "stacker_stack_4": (
        "Put one of the four boxes on the target spot, then move the hand away from it.",
        "Prefer the clip where a box is nearer the target spot, with the hand clear of it "
        "(about a box's width or more away); a box on the target with the hand still on it "
        f"counts nothing. {_ties('brings a box near the target spot')}",
    ),
    "swimmer_swimmer6": (
        "Swim so that the swimmer's nose reaches the target.",
        "Prefer the clip whose nose is at or nearer the target; the nearer, the better, even "
        f"from far away. {_RARE}",
    ),
    "swimmer_swimmer15": (
        "Swim so that the swimmer's nose reaches the target.",
        "Prefer the clip whose nose is at or nearer the target; the nearer, the better, even "
        f"from far away. {_RARE}",
    ),
    "walker_stand": (
        "Stand upright with the body high.",
        "Prefer the clip whose body is higher (nearly as high as standing straight counts "
        f"fully) and more upright; moving does not matter. {_RARE}",
    ),
    "walker_walk": (
        "Stand upright, then walk forward (to the right).",
        "First, prefer the walker that stands upright with its body high (nearly as high as "
        "standing straight). If both stand, or neither, prefer the one moving right faster, up "
        "to a walking pace (at 1×, about one of the posts behind it, a metre apart, going by "
        "each second); faster gains nothing. If the speeds are close, prefer the one that "
        f"covers more ground. {_RARE}",
    ),
    "walker_run": (
        "Stand upright, then run forward (to the right) as fast as possible.",
        "First, prefer the walker that stands upright with its body high (nearly as high as "
        "standing straight). If both stand, or neither, prefer the one moving right faster, up "
        "to a sprint (at 1×, about seven of the posts behind it, a metre apart, going by each "
        "second). If the speeds are close, prefer the one that covers more ground. "
        f"{_RARE}",
    ),
}

# ---- Metaworld v3 ------------------------------------------------------------------------
# A Sawyer arm at a table. The goal, where it is a place, is a small coloured ball. Every task's
# reward first pays for reaching (and where it says so, grasping) the object, then for moving it
# to the goal, and most for finishing.

_GRASP = ("Short of that: the object held and lifted beats the object touched, which beats the "
          "gripper only moving towards it.")
_PUSH = "Short of that: the object moved nearer the goal beats the gripper only reaching it."

_METAWORLD: dict[str, tuple[str, str]] = {
    "assembly": (
        "Pick up the ring by its handle and drop it over the peg.",
        f"Best: the ring down over the peg. {_GRASP} {_CLOSER}",
    ),
    "basketball": (
        "Pick up the ball and put it through the hoop.",
        f"Best: the ball in the hoop. {_GRASP} {_CLOSER}",
    ),
    "bin-picking": (
        "Pick the cube out of the left bin and put it in the right bin.",
        f"Best: the cube in the right bin. {_GRASP} {_CLOSER}",
    ),
    "box-close": (
        "Pick up the lid and put it on the box.",
        f"Best: the lid sitting on the box. {_GRASP} {_CLOSER}",
    ),
    "button-press-topdown": (
        "Press the button down from above.",
        "Best: the button pressed all the way in. Short of that: pressed partly beats "
        f"touched, which beats the gripper only moving towards it. {_CLOSER}",
    ),
    "button-press-topdown-wall": (
        "Press the button down from above; a low wall stands in front of it.",
        "Best: the button pressed all the way in. Short of that: pressed partly beats "
        f"touched, which beats the gripper only moving towards it. {_CLOSER}",
    ),
    "button-press": (
        "Push the button on the front of the box in, sideways.",
        "Best: the button pushed all the way in. Short of that: pushed partly beats touched, "
        f"which beats the gripper only moving towards it. {_CLOSER}",
    ),
    "button-press-wall": (
        "Push the button on the box in, reaching around the low wall in front of it.",
        "Best: the button pushed all the way in. Short of that: pushed partly beats touched, "
        f"which beats the gripper only moving towards it. {_CLOSER}",
    ),
    "coffee-button": (
        "Press the button on the coffee machine.",
        "Best: the button pushed all the way in. Short of that: pushed partly beats touched, "
        f"which beats the gripper only moving towards it. {_CLOSER}",
    ),
    "coffee-pull": (
        "Pull the mug out from under the coffee machine to the goal (the small ball).",
        f"Best: the mug at the goal. {_GRASP} {_CLOSER}",
    ),
    "coffee-push": (
        "Push the mug under the coffee machine's spout (the goal ball).",
        f"Best: the mug under the spout. {_GRASP} {_CLOSER}",
    ),
    "dial-turn": (
        "Turn the dial a quarter turn, to the goal mark.",
        "Best: the dial turned to the goal. Short of that: turned further beats turned less, "
        f"which beats the gripper only moving towards the dial. {_CLOSER}",
    ),
    "disassemble": (
        "Grasp the ring by its handle and lift it up off the peg.",
        f"Best: the ring lifted clear of the peg. {_GRASP} {_CLOSER}",
    ),
    "door-close": (
        "Swing the open door shut.",
        "Best: the door fully closed. Short of that: the door swung further shut beats one "
        f"pushed less, which beats the gripper only moving towards it. {_CLOSER}",
    ),
    "door-lock": (
        "Turn the lock on the door down, to locked.",
        "Best: the lock turned all the way down. Short of that: turned further beats turned "
        f"less, which beats the gripper only moving towards it. {_CLOSER}",
    ),
    "door-open": (
        "Open the door: pull it by its handle and swing it wide open.",
        "Best: the door swung open to the goal (the small ball). Short of that: the door "
        "opened further beats opened less; a firm grip on the handle beats only touching it, "
        f"which beats the gripper only moving towards it. {_CLOSER}",
    ),
    "door-unlock": (
        "Turn the lock on the door round, out of its locked position, to unlocked.",
        "Best: the lock turned all the way. Short of that: turned further beats turned less, "
        f"which beats the gripper only moving towards it. {_CLOSER}",
    ),
    "hand-insert": (
        "Grasp the small block and put it into the hole in the table.",
        f"Best: the block down in the hole. {_GRASP} {_CLOSER}",
    ),
    "drawer-close": (
        "Push the open drawer shut.",
        "Best: the drawer fully closed. Short of that: pushed further in beats pushed less, "
        f"which beats the gripper only moving towards it. {_CLOSER}",
    ),
    "drawer-open": (
        "Pull the drawer open by its handle.",
        "Best: the drawer pulled fully open. Short of that: opened further beats opened less; "
        "gripping the handle beats only moving towards it. " + _CLOSER,
    ),
    "faucet-open": (
        "Turn the faucet's handle round to open it, to the goal (the small ball).",
        "Best: the handle turned all the way to the goal. Short of that: turned further beats "
        f"turned less, which beats the gripper only moving towards it. {_CLOSER}",
    ),
    "faucet-close": (
        "Turn the faucet's handle round to close it, to the goal (the small ball).",
        "Best: the handle turned all the way to the goal. Short of that: turned further beats "
        f"turned less, which beats the gripper only moving towards it. {_CLOSER}",
    ),
    "hammer": (
        "Pick up the hammer by its handle and drive the nail into the box.",
        "Best: the nail knocked all the way in. Short of that: the hammer head held near the "
        f"nail, the right way up, beats the hammer only lifted. {_GRASP} {_CLOSER}",
    ),
    "handle-press-side": (
        "Press the handle on the side of the box down.",
        "Best: the handle pressed all the way down. Short of that: pressed further beats "
        f"pressed less, which beats the gripper only moving towards it. {_CLOSER}",
    ),
    "handle-press": (
        "Press the handle on the front of the box down.",
        "Best: the handle pressed all the way down. Short of that: pressed further beats "
        f"pressed less, which beats the gripper only moving towards it. {_CLOSER}",
    ),
    "handle-pull-side": (
        "Pull the handle on the side of the box up.",
        "Best: the handle pulled all the way up. Short of that: a grip under the handle "
        "lifting it beats touching it, which beats the gripper only moving towards it. "
        f"{_CLOSER}",
    ),
    "handle-pull": (
        "Pull the handle on the front of the box up.",
        "Best: the handle pulled all the way up. Short of that: a grip under the handle "
        "lifting it beats touching it, which beats the gripper only moving towards it. "
        f"{_CLOSER}",
    ),
    "lever-pull": (
        "Lift the lever up, a quarter turn, until it points up.",
        "Best: the lever raised to the goal. Short of that: the gripper under the lever's end "
        f"raising it beats the gripper only moving towards it. {_CLOSER}",
    ),
    "pick-place-wall": (
        "Pick up the puck, carry it over the wall and put it at the goal (the small ball).",
        f"Best: the puck at the goal. {_GRASP} {_CLOSER}",
    ),
    "pick-out-of-hole": (
        "Pick the peg up out of the hole and lift it to the goal (the small ball) above.",
        f"Best: the peg at the goal. {_GRASP} {_CLOSER}",
    ),
    "pick-place": (
        "Pick up the puck and carry it to the goal (the small ball), which may be in the air.",
        f"Best: the puck at the goal. {_GRASP} {_CLOSER}",
    ),
    "plate-slide": (
        "Slide the plate forward across the table into the goal net.",
        f"Best: the plate in the net. {_PUSH} {_CLOSER}",
    ),
    "plate-slide-side": (
        "Slide the plate sideways across the table into the goal net.",
        f"Best: the plate in the net. {_PUSH} {_CLOSER}",
    ),
    "plate-slide-back": (
        "Slide the plate back out of the net, towards the arm, to the goal.",
        f"Best: the plate at the goal. {_PUSH} {_CLOSER}",
    ),
    "plate-slide-back-side": (
        "Slide the plate sideways out of the net to the goal.",
        f"Best: the plate at the goal. {_PUSH} {_CLOSER}",
    ),
    "peg-insert-side": (
        "Pick up the peg and push it sideways into the hole in the box.",
        f"Best: the peg in the hole. {_GRASP} {_CLOSER}",
    ),
    "peg-unplug-side": (
        "Grasp the peg stuck in the side of the box and pull it out sideways.",
        "Best: the peg pulled out to the goal. Short of that: the peg gripped and moving out "
        f"beats only touched, which beats the gripper only moving towards it. {_CLOSER}",
    ),
    "soccer": (
        "Push the ball into the goal net.",
        f"Best: the ball in the net. {_PUSH} {_CLOSER}",
    ),
    "stick-push": (
        "Pick up the stick and use it to push the thermos to the goal.",
        "Best: the thermos at the goal, pushed by the stick in hand. Short of that: the stick "
        "held and brought to the thermos beats the stick only lifted, which beats the gripper "
        f"only moving towards it. {_CLOSER}",
    ),
    "stick-pull": (
        "Pick up the stick, hook it into the thermos's handle and pull the thermos to the goal.",
        "Best: the thermos pulled to the goal. Short of that: the stick held and hooked in the "
        "handle beats the stick only lifted, which beats the gripper only moving towards it. "
        f"{_CLOSER}",
    ),
    "push": (
        "Push the puck across the table to the goal (the small ball).",
        f"Best: the puck at the goal. {_PUSH} Holding the puck is fine. {_CLOSER}",
    ),
    "push-wall": (
        "Push the puck around the wall to the goal (the small ball).",
        f"Best: the puck at the goal. {_PUSH} Holding the puck is fine. {_CLOSER}",
    ),
    "push-back": (
        "Push the puck back, towards the arm, to the goal (the small ball).",
        f"Best: the puck at the goal. {_PUSH} Holding the puck is fine. {_CLOSER}",
    ),
    "reach": (
        "Move the gripper to the goal (the small ball).",
        "Prefer the clip whose gripper is at the goal, or nearer it, for longer.",
    ),
    "reach-wall": (
        "Move the gripper over the wall to the goal (the small ball) behind it.",
        "Prefer the clip whose gripper is at the goal, or nearer it, for longer.",
    ),
    "shelf-place": (
        "Pick up the puck and put it on the shelf, at the goal.",
        f"Best: the puck on the shelf at the goal. {_GRASP} {_CLOSER}",
    ),
    "sweep-into": (
        "Sweep the cube across the table into the hole.",
        f"Best: the cube in the hole. {_PUSH} Holding the cube is fine. {_CLOSER}",
    ),
    "sweep": (
        "Sweep the cube across the table and off its edge, to the goal.",
        f"Best: the cube swept off the edge to the goal. {_PUSH} Holding the cube is fine. "
        f"{_CLOSER}",
    ),
    "window-open": (
        "Slide the window open by its handle.",
        "Best: the window slid fully open. Short of that: slid further beats slid less, which "
        f"beats the gripper only moving towards the handle. {_CLOSER}",
    ),
    "window-close": (
        "Slide the open window shut by its handle.",
        "Best: the window slid fully shut. Short of that: slid further beats slid less, which "
        f"beats the gripper only moving towards the handle. {_CLOSER}",
    ),
}

# Most Metaworld rewards pay for the gripper's distance to the object at every step, so two
# clips almost never tie exactly (`trainer.tie_check`: no exact tie among random or idle pairs).
# These do tie: dial-turn and drawer-close pay the same while the arm stays still, and
# pick-place-wall and shelf-place pay nothing until the puck is between the fingers (every
# random pair ties).
_CAGED = ("Short of that: the puck held and lifted beats the puck only between the fingers; "
          "moving the gripper towards it counts nothing.")
_METAWORLD_TIES = {
    "dial-turn": _ties("moves the gripper at all"),
    "drawer-close": _ties("moves the gripper at all"),
    "pick-place-wall": _ties("gets the puck between the gripper's open fingers", True),
    "shelf-place": _ties("gets the puck between the gripper's open fingers", True),
}
_METAWORLD["pick-place-wall"] = (_METAWORLD["pick-place-wall"][0],
                                 f"Best: the puck at the goal. {_CAGED}")
_METAWORLD["shelf-place"] = (_METAWORLD["shelf-place"][0],
                             f"Best: the puck on the shelf at the goal. {_CAGED}")
_METAWORLD = {name: (goal, f"{how} {_METAWORLD_TIES.get(name, _RARE)}")
              for name, (goal, how) in _METAWORLD.items()}

_BY_FAMILY = {"dmc": _DMC, "metaworld": _METAWORLD}


def specific_instruction(task: str) -> str | None:
    """The task's own instruction ("goal" line, then what decides), or None for a task
    without one."""
    family, _, name = task.partition(":")
    entry = _BY_FAMILY.get(family, {}).get(name)
    return None if entry is None else f"{entry[0]}\n{entry[1]}"


def tie_sentence(task: str) -> str:
    """The last sentence of the task's own (or generic) instruction: what ties look like."""
    text = default_instruction(task)
    for kind_end in (_OFTEN_TAIL, ):
        if text.endswith(kind_end):
            body = text[:-len(kind_end)]
            return body[body.rindex("If neither"):] + kind_end
    if text.endswith(_RARE):
        return _RARE
    return text[text.rindex("If neither"):] if "If neither" in text else ""


def tie_kind(task: str) -> str:
    """What the task's instruction says of exact ties: "often" (most early pairs), "sometimes"
    (when neither clip does what the reward pays for) or "rare"; "" when it says nothing."""
    sentence = tie_sentence(task)
    if sentence.endswith(_OFTEN_TAIL):
        return "often"
    if sentence == _RARE:
        return "rare"
    return "sometimes" if sentence.endswith("they are equally good.") else ""


def generic_instruction(task: str) -> str:
    """An instruction built from the task's name alone, for a task without its own."""
    name = task.partition(":")[2] or task
    words = name.replace("_", " ").replace("-", " ").strip() or "the task"
    return (f"Do the task “{words}” as well as possible.\n"
            "Prefer the clip that gets nearer to doing it, or does it for longer. "
            f"{_NEITHER}")


def default_instruction(task: str) -> str:
    """What a run of `task` shows when its operator gave no instruction of its own."""
    return specific_instruction(task) or generic_instruction(task)


def run_instruction(task: str, override: str | None) -> str:
    """The instruction a run shows: the operator's text when there is one, else the task's."""
    text = (override or "").strip()
    return text or default_instruction(task)


def clean_instruction(text: str) -> str:
    """An operator's instruction as stored: line ends normalised, outer blanks stripped;
    ValueError naming the problem when it is empty, too long or holds control characters."""
    text = text.replace("\r\n", "\n").replace("\r", "\n").strip()
    if not text:
        raise ValueError("is empty; leave it out (or null) to use the task's own instruction")
    if len(text) > MAX_CHARS:
        raise ValueError(f"is {len(text)} characters long; at most {MAX_CHARS} are stored")
    bad = sorted({f"U+{ord(c):04X}" for c in text if ord(c) < 32 and c not in "\n\t"})
    if bad:
        raise ValueError(f"holds control characters ({', '.join(bad)})")
    return text


def instruction_sha256(text: str) -> str:
    """The hex sha256 of an instruction's UTF-8 text: the same text, the same hash."""
    return hashlib.sha256(text.encode()).hexdigest()
