"""msfnet.bench"""
