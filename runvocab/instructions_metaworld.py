"""Metaworld v3's instructions to labellers (`runvocab.instructions`), written from each task's
`compute_reward`."""

from __future__ import annotations

from runvocab.tie_sentences import CLOSER, RARE, ties

# A Sawyer arm at a table. The goal, where it is a place, is a small coloured ball. Every task's
# reward first pays for reaching (and where it says so, grasping) the object, then for moving it
# to the goal, and most for finishing.

_GRASP = ("Short of that: the object held and lifted beats the object touched, which beats the "
          "gripper only moving towards it.")
_PUSH = "Short of that: the object moved nearer the goal beats the gripper only reaching it."

METAWORLD: dict[str, tuple[str, str]] = {
    "assembly": (
        "Pick up the ring by its handle and drop it over the peg.",
        f"Best: the ring down over the peg. {_GRASP} {CLOSER}",
    ),
    "basketball": (
        "Pick up the ball and put it through the hoop.",
        f"Best: the ball in the hoop. {_GRASP} {CLOSER}",
    ),
    "bin-picking": (
        "Pick the cube out of the left bin and put it in the right bin.",
        f"Best: the cube in the right bin. {_GRASP} {CLOSER}",
    ),
    "box-close": (
        "Pick up the lid and put it on the box.",
        f"Best: the lid sitting on the box. {_GRASP} {CLOSER}",
    ),
    "button-press-topdown": (
        "Press the button down from above.",
        "Best: the button pressed all the way in. Short of that: pressed partly beats "
        f"touched, which beats the gripper only moving towards it. {CLOSER}",
    ),
    "button-press-topdown-wall": (
        "Press the button down from above; a low wall stands in front of it.",
        "Best: the button pressed all the way in. Short of that: pressed partly beats "
        f"touched, which beats the gripper only moving towards it. {CLOSER}",
    ),
    "button-press": (
        "Push the button on the front of the box in, sideways.",
        "Best: the button pushed all the way in. Short of that: pushed partly beats touched, "
        f"which beats the gripper only moving towards it. {CLOSER}",
    ),
    "button-press-wall": (
        "Push the button on the box in, reaching around the low wall in front of it.",
        "Best: the button pushed all the way in. Short of that: pushed partly beats touched, "
        f"which beats the gripper only moving towards it. {CLOSER}",
    ),
    "coffee-button": (
        "Press the button on the coffee machine.",
        "Best: the button pushed all the way in. Short of that: pushed partly beats touched, "
        f"which beats the gripper only moving towards it. {CLOSER}",
    ),
    "coffee-pull": (
        "Pull the mug out from under the coffee machine to the goal (the small ball).",
        f"Best: the mug at the goal. {_GRASP} {CLOSER}",
    ),
    "coffee-push": (
        "Push the mug under the coffee machine's spout (the goal ball).",
        f"Best: the mug under the spout. {_GRASP} {CLOSER}",
    ),
    "dial-turn": (
        "Turn the dial a quarter turn, to the goal mark.",
        "Best: the dial turned to the goal. Short of that: turned further beats turned less, "
        f"which beats the gripper only moving towards the dial. {CLOSER}",
    ),
    "disassemble": (
        "Grasp the ring by its handle and lift it up off the peg.",
        f"Best: the ring lifted clear of the peg. {_GRASP} {CLOSER}",
    ),
    "door-close": (
        "Swing the open door shut.",
        "Best: the door fully closed. Short of that: the door swung further shut beats one "
        f"pushed less, which beats the gripper only moving towards it. {CLOSER}",
    ),
    "door-lock": (
        "Turn the lock on the door down, to locked.",
        "Best: the lock turned all the way down. Short of that: turned further beats turned "
        f"less, which beats the gripper only moving towards it. {CLOSER}",
    ),
    "door-open": (
        "Open the door: pull it by its handle and swing it wide open.",
        "Best: the door swung open to the goal (the small ball). Short of that: the door "
        "opened further beats opened less; a firm grip on the handle beats only touching it, "
        f"which beats the gripper only moving towards it. {CLOSER}",
    ),
    "door-unlock": (
        "Turn the lock on the door round, out of its locked position, to unlocked.",
        "Best: the lock turned all the way. Short of that: turned further beats turned less, "
        f"which beats the gripper only moving towards it. {CLOSER}",
    ),
    "hand-insert": (
        "Grasp the small block and put it into the hole in the table.",
        f"Best: the block down in the hole. {_GRASP} {CLOSER}",
    ),
    "drawer-close": (
        "Push the open drawer shut.",
        "Best: the drawer fully closed. Short of that: pushed further in beats pushed less, "
        f"which beats the gripper only moving towards it. {CLOSER}",
    ),
    "drawer-open": (
        "Pull the drawer open by its handle.",
        "Best: the drawer pulled fully open. Short of that: opened further beats opened less; "
        "gripping the handle beats only moving towards it. " + CLOSER,
    ),
    "faucet-open": (
        "Turn the faucet's handle round to open it, to the goal (the small ball).",
        "Best: the handle turned all the way to the goal. Short of that: turned further beats "
        f"turned less, which beats the gripper only moving towards it. {CLOSER}",
    ),
    "faucet-close": (
        "Turn the faucet's handle round to close it, to the goal (the small ball).",
        "Best: the handle turned all the way to the goal. Short of that: turned further beats "
        f"turned less, which beats the gripper only moving towards it. {CLOSER}",
    ),
    "hammer": (
        "Pick up the hammer by its handle and drive the nail into the box.",
        "Best: the nail knocked all the way in. Short of that: the hammer head held near the "
        f"nail, the right way up, beats the hammer only lifted. {_GRASP} {CLOSER}",
    ),
    "handle-press-side": (
        "Press the handle on the side of the box down.",
        "Best: the handle pressed all the way down. Short of that: pressed further beats "
        f"pressed less, which beats the gripper only moving towards it. {CLOSER}",
    ),
    "handle-press": (
        "Press the handle on the front of the box down.",
        "Best: the handle pressed all the way down. Short of that: pressed further beats "
        f"pressed less, which beats the gripper only moving towards it. {CLOSER}",
    ),
    "handle-pull-side": (
        "Pull the handle on the side of the box up.",
        "Best: the handle pulled all the way up. Short of that: a grip under the handle "
        "lifting it beats touching it, which beats the gripper only moving towards it. "
        f"{CLOSER}",
    ),
    "handle-pull": (
        "Pull the handle on the front of the box up.",
        "Best: the handle pulled all the way up. Short of that: a grip under the handle "
        "lifting it beats touching it, which beats the gripper only moving towards it. "
        f"{CLOSER}",
    ),
    "lever-pull": (
        "Lift the lever up, a quarter turn, until it points up.",
        "Best: the lever raised to the goal. Short of that: the gripper under the lever's end "
        f"raising it beats the gripper only moving towards it. {CLOSER}",
    ),
    "pick-place-wall": (
        "Pick up the puck, carry it over the wall and put it at the goal (the small ball).",
        f"Best: the puck at the goal. {_GRASP} {CLOSER}",
    ),
    "pick-out-of-hole": (
        "Pick the peg up out of the hole and lift it to the goal (the small ball) above.",
        f"Best: the peg at the goal. {_GRASP} {CLOSER}",
    ),
    "pick-place": (
        "Pick up the puck and carry it to the goal (the small ball), which may be in the air.",
        f"Best: the puck at the goal. {_GRASP} {CLOSER}",
    ),
    "plate-slide": (
        "Slide the plate forward across the table into the goal net.",
        f"Best: the plate in the net. {_PUSH} {CLOSER}",
    ),
    "plate-slide-side": (
        "Slide the plate sideways across the table into the goal net.",
        f"Best: the plate in the net. {_PUSH} {CLOSER}",
    ),
    "plate-slide-back": (
        "Slide the plate back out of the net, towards the arm, to the goal.",
        f"Best: the plate at the goal. {_PUSH} {CLOSER}",
    ),
    "plate-slide-back-side": (
        "Slide the plate sideways out of the net to the goal.",
        f"Best: the plate at the goal. {_PUSH} {CLOSER}",
    ),
    "peg-insert-side": (
        "Pick up the peg and push it sideways into the hole in the box.",
        f"Best: the peg in the hole. {_GRASP} {CLOSER}",
    ),
    "peg-unplug-side": (
        "Grasp the peg stuck in the side of the box and pull it out sideways.",
        "Best: the peg pulled out to the goal. Short of that: the peg gripped and moving out "
        f"beats only touched, which beats the gripper only moving towards it. {CLOSER}",
    ),
    "soccer": (
        "Push the ball into the goal net.",
        f"Best: the ball in the net. {_PUSH} {CLOSER}",
    ),
    "stick-push": (
        "Pick up the stick and use it to push the thermos to the goal.",
        "Best: the thermos at the goal, pushed by the stick in hand. Short of that: the stick "
        "held and brought to the thermos beats the stick only lifted, which beats the gripper "
        f"only moving towards it. {CLOSER}",
    ),
    "stick-pull": (
        "Pick up the stick, hook it into the thermos's handle and pull the thermos to the goal.",
        "Best: the thermos pulled to the goal. Short of that: the stick held and hooked in the "
        "handle beats the stick only lifted, which beats the gripper only moving towards it. "
        f"{CLOSER}",
    ),
    "push": (
        "Push the puck across the table to the goal (the small ball).",
        f"Best: the puck at the goal. {_PUSH} Holding the puck is fine. {CLOSER}",
    ),
    "push-wall": (
        "Push the puck around the wall to the goal (the small ball).",
        f"Best: the puck at the goal. {_PUSH} Holding the puck is fine. {CLOSER}",
    ),
    "push-back": (
        "Push the puck back, towards the arm, to the goal (the small ball).",
        f"Best: the puck at the goal. {_PUSH} Holding the puck is fine. {CLOSER}",
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
        f"Best: the puck on the shelf at the goal. {_GRASP} {CLOSER}",
    ),
    "sweep-into": (
        "Sweep the cube across the table into the hole.",
        f"Best: the cube in the hole. {_PUSH} Holding the cube is fine. {CLOSER}",
    ),
    "sweep": (
        "Sweep the cube across the table and off its edge, to the goal.",
        f"Best: the cube swept off the edge to the goal. {_PUSH} Holding the cube is fine. "
        f"{CLOSER}",
    ),
    "window-open": (
        "Slide the window open by its handle.",
        "Best: the window slid fully open. Short of that: slid further beats slid less, which "
        f"beats the gripper only moving towards the handle. {CLOSER}",
    ),
    "window-close": (
        "Slide the open window shut by its handle.",
        "Best: the window slid fully shut. Short of that: slid further beats slid less, which "
        f"beats the gripper only moving towards the handle. {CLOSER}",
    ),
}

# Most Metaworld rewards pay for the gripper's distance to the object at every step, so two
# clips almost never tie exactly (`trainer.tie_check`: no exact tie among random or idle pairs).
# These do tie: dial-turn and drawer-close pay the same while the arm stays still, and
# pick-place-wall and shelf-place pay nothing until the puck is between the fingers (every
# random pair ties).
_CAGED = ("Short of that: the puck held and lifted beats the puck only between the fingers; "
          "moving the gripper towards it counts nothing.")
_TIES = {
    "dial-turn": ties("moves the gripper at all"),
    "drawer-close": ties("moves the gripper at all"),
    "pick-place-wall": ties("gets the puck between the gripper's open fingers", True),
    "shelf-place": ties("gets the puck between the gripper's open fingers", True),
}
METAWORLD["pick-place-wall"] = (METAWORLD["pick-place-wall"][0],
                                 f"Best: the puck at the goal. {_CAGED}")
METAWORLD["shelf-place"] = (METAWORLD["shelf-place"][0],
                             f"Best: the puck on the shelf at the goal. {_CAGED}")
METAWORLD = {name: (goal, f"{how} {_TIES.get(name, RARE)}")
              for name, (goal, how) in METAWORLD.items()}
